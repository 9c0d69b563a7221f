"""The files of a training run's folder (``trainer train --out RUN``), named once here: what
the trainer writes, and what ``trainer eval``, the farm dashboard and the benchmarks read.
Plain names and the readers of its log lines, free of torch (the dashboard reads runs
without the train extra).

- ``config.json``: the run's :class:`trainer.training.config.TrainConfig`;
- ``log.jsonl``: a line every ``--log-every`` steps (loss, images/s, data wait, rate);
- ``val.jsonl``, ``val.png``, ``val-best.json``: held-out scores, their picture grid, and the
  best score's per-sample PSNRs (``trainer.training.runlog``);
- ``tb/``: TensorBoard events; ``checkpoints/``: ``step-NNNNNNNN.pt`` and ``best.pt``
  (``trainer.checkpoint``);
- ``eval.json``, ``eval.png``: ``trainer eval``'s scores and grid of the run;
- ``samples/rank-R.txt``: each rank's sample ids (``--log-samples``).
"""

from __future__ import annotations

import json
from pathlib import Path

CONFIG = "config.json"
LOG = "log.jsonl"
VAL = "val.jsonl"
VAL_GRID = "val.png"
BEST_SCORES = "val-best.json"
TENSORBOARD = "tb"
CHECKPOINTS = "checkpoints"
BEST = "best.pt"
EVAL = "eval.json"
EVAL_GRID = "eval.png"
SAMPLES = "samples"


def read_log(run: Path, name: str = LOG) -> list[dict]:
    """The run's log lines, or those of its ``name`` (none for a file not written yet; a
    torn last line, while it is written, is skipped)."""
    path = Path(run) / name
    if not path.exists():
        return []
    out = []
    for line in path.read_text().splitlines():
        try:
            out.append(json.loads(line))
        except json.JSONDecodeError:
            continue
    return out


def kept_lines(records: list[dict]) -> list[dict]:
    """The :data:`LOG` lines of the steps a run kept, in order. A run resumed from a
    checkpoint logs again the steps after it: its first line's window starts at the
    checkpoint's step, and the lines of the cut process past that step are dropped."""
    kept: list[dict] = []
    for r in records:
        if not r.get("images_per_second"):
            continue
        while kept and kept[-1]["step"] > r["step"] - r["steps"]:
            kept.pop()
        kept.append(r)
    return kept


def loop_seconds(records: list[dict]) -> float:
    """Seconds the trainer spent in its step loop, from its :data:`LOG` lines: each kept
    line's images over its images/s (held-out scoring left out), so a run's time is that of
    the steps it kept, however often it was cut and resumed."""
    return sum(r["images"] / r["images_per_second"] for r in kept_lines(records))


def samples_file(rank: int) -> str:
    """Rank ``rank``'s sample-id file, under :data:`SAMPLES`."""
    return f"rank-{rank}.txt"
