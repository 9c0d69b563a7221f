"""What the dashboard knows of trainer runs: each run folder's ``log.jsonl`` (loss, images/s,
data wait), ``val.jsonl`` and ``val.png`` (held-out scores and pictures while it trains),
``checkpoints/``, and ``eval.json`` / ``eval.png`` where ``trainer eval`` wrote them. A
``--runs`` folder is a run (it holds ``log.jsonl`` or ``config.json``) or a folder of runs.
Runs are named ``<runs index>/<path below it>`` in URLs and labelled with the folder as given
plus that path on the page and in the metrics."""

from __future__ import annotations

import json
from pathlib import Path

#: log lines kept for a curve (evenly thinned): a long run's log has one a few seconds
CURVE_POINTS = 600


def is_run(path: Path) -> bool:
    return (path / "log.jsonl").exists() or (path / "config.json").exists()


def find_runs(base: Path) -> list[str]:
    if is_run(base):
        return ["."]
    if not base.is_dir():
        return []
    return [c.name for c in sorted(base.iterdir()) if c.is_dir() and is_run(c)]


def read_log(run: Path, name: str = "log.jsonl") -> list[dict]:
    """The run's log lines, or those of its ``name`` (a torn last line, while it is written,
    is skipped)."""
    path = run / name
    if not path.exists():
        return []
    out = []
    for line in path.read_text().splitlines():
        try:
            out.append(json.loads(line))
        except json.JSONDecodeError:
            continue
    return out


def thin(rows: list, limit: int = CURVE_POINTS) -> list:
    if len(rows) <= limit:
        return rows
    step = len(rows) / limit
    return [rows[int(i * step)] for i in range(limit)] + [rows[-1]]


def run_summary(name: str, run: Path, label: str | None = None) -> dict:
    """What the runs page and the metrics show of ``run``: ``name`` is its key in URLs,
    ``label`` its name on the page and in the metrics (``name`` when not given)."""
    log = read_log(run)
    last = log[-1] if log else {}
    val = read_log(run, "val.jsonl")
    ckpts = sorted((run / "checkpoints").glob("*.pt")) if (run / "checkpoints").is_dir() else []
    ev = None
    if (run / "eval.json").exists():
        try:
            ev = json.loads((run / "eval.json").read_text())
        except json.JSONDecodeError:
            ev = None
    return {
        "name": name,
        "label": label or name,
        "path": str(run),
        "step": last.get("step"),
        "epoch": last.get("epoch"),
        "loss": last.get("loss"),
        "images_per_second": last.get("images_per_second"),
        "data_wait": last.get("data_wait"),
        "updated": last.get("time"),
        "log": thin(log),
        "val": thin(val),
        "val_last": val[-1] if val else None,
        "val_best": max(val, key=lambda r: r.get("psnr", float("-inf"))) if val else None,
        "checkpoints": [
            {"name": c.name, "bytes": c.stat().st_size, "mtime": c.stat().st_mtime} for c in ckpts
        ],
        "eval": ev,
        "eval_grid": (run / "eval.png").exists(),
        "val_grid": (run / "val.png").exists(),
    }
