"""What the dashboard knows of trainer runs: each run folder's ``config.json`` (the settings
it trains with), ``log.jsonl`` (loss, images/s, data wait), ``val.jsonl`` and ``val.png``
(held-out scores and pictures while it trains), ``checkpoints/``, and ``eval.json`` /
``eval.png`` where ``trainer eval`` wrote them. A ``--runs`` folder is a run (it holds
``log.jsonl`` or ``config.json``) or a folder of runs. Runs are named ``<runs index>/<path
below it>`` in URLs and labelled with the folder as given plus that path on the page and in
the metrics."""

from __future__ import annotations

import json
import os
import shlex
from pathlib import Path

from trainer import runfiles

#: log lines kept for a curve (evenly thinned): a long run's log has one a few seconds
CURVE_POINTS = 600

#: the settings of a run that the runs page shows, in order: (``config.json`` key, label)
SETTINGS = (
    ("store", "stores"),
    ("init", "fine-tuned from"),
    ("recipe", "recipe"),
    ("model", "model"),
    ("inputs", "scene cues"),
    ("norm", "normalisation"),
    ("head", "full-resolution head"),
    ("residual", "residual"),
    ("width", "width"),
    ("skips", "skips"),
    ("roughness_channels", "roughness channels"),
    ("loss", "loss"),
    ("batch_size", "batch a rank"),
    ("lr", "lr"),
    ("lr_schedule", "schedule"),
    ("warmup_steps", "warm-up steps"),
    ("ema_decay", "weight average"),
    ("epochs", "epochs"),
    ("max_steps", "max steps"),
    ("holdout_fraction", "held out"),
    ("holdout_seed", "held-out seed"),
    ("seed", "seed"),
    ("exposure", "exposure"),
)


def is_run(path: Path) -> bool:
    return (path / runfiles.LOG).exists() or (path / runfiles.CONFIG).exists()


def find_runs(base: Path) -> list[str]:
    if is_run(base):
        return ["."]
    if not base.is_dir():
        return []
    return [c.name for c in sorted(base.iterdir()) if c.is_dir() and is_run(c)]


def read_config(run: Path) -> dict:
    """The run's ``config.json`` (``{}`` when it has none, or one being written)."""
    try:
        config = json.loads((run / runfiles.CONFIG).read_text())
    except (OSError, json.JSONDecodeError):
        return {}
    return config if isinstance(config, dict) else {}


def settings(config: dict) -> dict[str, object]:
    """``{label: value}`` of the :data:`SETTINGS` the config has, in their order: stores by
    their names (the full addresses are in the run's config), a weight average of 0 as
    none."""
    out = {}
    for key, label in SETTINGS:
        if key not in config:
            continue
        value = config[key]
        if key == "store":
            value = ", ".join(str(s).rstrip("/").rsplit("/", 1)[-1] for s in value)
        elif key == "ema_decay":
            value = value or None
        elif key == "inputs":
            value = ", ".join(value) or "none"
        elif key == "init" and value:
            value = _short_checkpoint(value)
        out[label] = value
    return out


def _short_checkpoint(path: str) -> str:
    """A run folder by its name, a checkpoint file as ``RUN/FILE``."""
    p = Path(path)
    return f"{p.parent.parent.name}/{p.name}" if p.parent.name == runfiles.CHECKPOINTS else p.name


#: the label of a scored run's held-out samples (``heldout_set`` of its last score): runs
#: whose values differ scored other samples, and their curves do not compare
HELDOUT = "held-out samples"


def differing(runs: list[dict]) -> list[str]:
    """The labels of the settings whose values differ between ``runs`` (their ``settings``),
    in :data:`SETTINGS` order, then :data:`HELDOUT`; none with fewer than two runs."""
    if len(runs) < 2:
        return []
    labels = [*(label for _, label in SETTINGS), HELDOUT]
    return [k for k in labels if len({repr(r["settings"].get(k)) for r in runs}) > 1]


def compare_commands(runs: list[dict]) -> list[dict]:
    """The ``trainer eval`` commands that score scored ``runs`` sample by sample, each against
    the first, with intervals: one for each set of two or more runs with checkpoints that name
    the same held-out samples (:data:`HELDOUT`), in page order, as ``{"labels", "command"}``."""
    groups: dict[str, list[dict]] = {}
    for r in runs:
        held = r["settings"].get(HELDOUT)
        if r["val"] and r["checkpoints"] and held is not None:
            groups.setdefault(held, []).append(r)
    return [
        {
            "labels": [r["label"] for r in group],
            "command": "trainer eval "
            + " ".join(f"--checkpoint {shlex.quote(r['path'])}" for r in group),
        }
        for group in groups.values()
        if len(group) > 1
    ]


def finetune_commands(runs: list[dict]) -> list[dict]:
    """For each scored run with checkpoints that is fine-tuned from a network still where it
    says: the ``trainer eval`` commands that measure what fine-tuning gained (on the run's
    held-out samples) and what it forgot (on those of the network it starts from)."""
    out = []
    for r in runs:
        if not (r.get("init") and r["val"] and r["checkpoints"] and os.path.exists(r["init"])):
            continue
        tuned, first = shlex.quote(r["path"]), shlex.quote(r["init"])
        out.append({
            "label": r["label"],
            "gained": f"trainer eval --checkpoint {tuned} --checkpoint {first}",
            "forgot": f"trainer eval --checkpoint {first} --checkpoint {tuned}",
        })  # fmt: skip
    return out


def thin(rows: list, limit: int = CURVE_POINTS) -> list:
    if len(rows) <= limit:
        return rows
    step = len(rows) / limit
    return [rows[int(i * step)] for i in range(limit)] + [rows[-1]]


def run_summary(name: str, run: Path, label: str | None = None) -> dict:
    """What the runs page and the metrics show of ``run``: ``name`` is its key in URLs,
    ``label`` its name on the page and in the metrics (``name`` when not given)."""
    log = runfiles.read_log(run)
    last = log[-1] if log else {}
    val = runfiles.read_log(run, runfiles.VAL)
    ckpts = sorted((run / runfiles.CHECKPOINTS).glob("*.pt"))
    ev = None
    if (run / runfiles.EVAL).exists():
        try:
            ev = json.loads((run / runfiles.EVAL).read_text())
        except json.JSONDecodeError:
            ev = None
    config = read_config(run)
    shown = settings(config)
    if val and "heldout_set" in val[-1]:
        shown[HELDOUT] = val[-1]["heldout_set"]
    return {
        "name": name,
        "label": label or name,
        "path": os.path.abspath(run),  # so that the compare command works from any folder
        "settings": shown,
        "init": config.get("init"),  # the network it is fine-tuned from: a run or checkpoint
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
        "eval_grid": (run / runfiles.EVAL_GRID).exists(),
        "val_grid": (run / runfiles.VAL_GRID).exists(),
    }
