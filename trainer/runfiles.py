"""The files of a training run's folder (``trainer train --out RUN``), named once here: what
the trainer writes, and what ``trainer eval``, the farm dashboard and the benchmarks read.
Plain names, free of torch (the dashboard reads runs without the train extra).

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


def samples_file(rank: int) -> str:
    """Rank ``rank``'s sample-id file, under :data:`SAMPLES`."""
    return f"rank-{rank}.txt"
