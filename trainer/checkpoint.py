"""Checkpoints of a run: ``RUNDIR/checkpoints/step-NNNNNNNN.pt``, written atomically.

A checkpoint is a plain dict loadable with ``torch.load(..., weights_only=True)``: ``model`` and
``optimizer`` state dicts, ``step``, ``epoch`` and ``position`` (the loader state: the next
global position in that epoch's order, see ``trainer.training.data``), ``config`` (the run's
:class:`trainer.training.config.TrainConfig`), ``model_config``, ``tonemap`` and ``catalog``
(the stores, shards and held-out materials the run trains on), and ``screen_uv`` when the stores
have one (the bytes of ``render_jobs.screen_uv.FILE``: the checkpoint alone then maps any
material to the network's input, ``trainer.rendering.mapping``), and ``best`` (``{"step",
"psnr"}``: the best held-out score at a checkpoint so far, or none), and ``ema`` when the run
averages its weights (:meth:`trainer.training.ema.WeightAverage.state_dict`: the weights the
checkpoint renders with, :func:`weights`). A slimmed checkpoint (``trainer.slim``) keeps one set
of weights as ``model``, with no ``optimizer`` or ``ema``, and says which in ``slim``. Written
to a temporary file in the same folder, fsynced, then renamed into place; the newest ``keep``
are kept, and ``checkpoints/best.pt`` is a second name of the one with the best held-out PSNR
(:func:`keep_best`), kept when the rotation drops its step file.
"""

from __future__ import annotations

import os
import re
import shutil
from pathlib import Path

from shaderball.errors import UserError
from storage.backend import write_atomic
from trainer import runfiles

PATTERN = re.compile(r"^step-(\d{8})\.pt$")
#: the checkpoint with the best held-out PSNR, beside the step files (``trainer.training.train``)
BEST = runfiles.BEST

#: which of a checkpoint's weights a command runs (:func:`weights`)
WEIGHTS = ("auto", "average", "trained")


class CheckpointError(UserError, RuntimeError):
    """A checkpoint is missing, unreadable or not one of ours."""


def chosen(state: dict, which: str = "auto") -> str:
    """Which of a checkpoint's weights ``which`` (one of :data:`WEIGHTS`) names: ``trained``
    (the optimizer's) or ``average`` (the moving average of a run with ``--ema-decay``);
    ``auto`` is the average when there is one: what render, eval, the viewer and export
    use."""
    if which not in WEIGHTS:
        raise ValueError(f"weights must be one of {', '.join(WEIGHTS)}, not {which!r}")
    if (slim := state.get("slim")) is not None:  # one set: the one it was slimmed from
        if which not in ("auto", slim["weights"]):
            raise CheckpointError(
                f"a slimmed checkpoint keeps the {slim['weights']} weights alone (slim the "
                f"run's own checkpoint with --weights {which} for those)"
            )
        return slim["weights"]
    kept = state.get("ema") is not None
    if which == "average" and not kept:
        raise CheckpointError(
            f"the run kept no average of its weights at step {state.get('step')} "
            "(train with --ema-decay)"
        )
    return "average" if kept and which != "trained" else "trained"


def weights(state: dict, which: str = "auto") -> dict:
    """The model state dict of the checkpoint's weights that ``which`` names (:func:`chosen`)."""
    kept = chosen(state, which)
    return state["ema"]["weights"] if kept == "average" and "slim" not in state else state["model"]


def folder(run_dir: str | os.PathLike) -> Path:
    return Path(run_dir) / runfiles.CHECKPOINTS


def listing(run_dir: str | os.PathLike) -> list[Path]:
    """The run's checkpoints, oldest first."""
    d = folder(run_dir)
    if not d.is_dir():
        return []
    return sorted(p for p in d.iterdir() if PATTERN.match(p.name))


def latest(run_dir: str | os.PathLike) -> Path | None:
    found = listing(run_dir)
    return found[-1] if found else None


def save(run_dir: str | os.PathLike, state: dict, keep: int = 3) -> Path:
    """Write ``state`` as the checkpoint of ``state["step"]``; drop all but the newest ``keep``."""
    d = folder(run_dir)
    d.mkdir(parents=True, exist_ok=True)
    path = d / f"step-{int(state['step']):08d}.pt"
    import torch  # the train extra: this module is imported by every trainer command

    write_atomic(path, lambda f: torch.save(state, f))
    for old in listing(run_dir)[:-keep] if keep > 0 else []:
        old.unlink(missing_ok=True)
    return path


def keep_best(path: Path) -> Path:
    """Name the checkpoint ``path`` :data:`BEST` too, replacing the one named so before in one
    rename: a hard link (a copy where the file system has none). The link is made under one
    fixed temporary name (one process writes a run's checkpoints), so one a kill left
    behind is removed by the next call."""
    best = path.parent / BEST
    tmp = path.parent / f".{BEST}.tmp"
    tmp.unlink(missing_ok=True)
    try:
        os.link(path, tmp)
    except OSError:
        shutil.copyfile(path, tmp)
    os.replace(tmp, best)
    return best


REQUIRED = ("model", "step", "epoch", "position", "config", "model_config", "tonemap", "catalog")


#: the first bytes of every file ``torch.save`` writes (a zip archive)
TORCH_MAGIC = b"PK\x03\x04"


def why_unreadable(path: Path, exc: Exception) -> str:
    """One line on why ``torch.load`` refused ``path``: not a torch file at all, or the
    unpickler's own reason without torch's advice to load untrusted files unsafely."""
    with open(path, "rb") as f:
        if f.read(len(TORCH_MAGIC)) != TORCH_MAGIC:
            return "not a file torch.save writes"
    text = str(exc)
    marker = "WeightsUnpickler error:"
    if marker in text:
        text = text[text.index(marker) + len(marker) :]
    lines = [line.strip() for line in text.splitlines() if line.strip()]
    return lines[0] if lines else type(exc).__name__


def resolve(path: str | os.PathLike) -> Path:
    """The checkpoint file ``path`` names: the file itself, or a run folder's latest."""
    p = Path(path)
    if p.is_dir():
        found = latest(p)
        if found is None:
            raise CheckpointError(f"{p}: no checkpoints in {folder(p)}")
        p = found
    return p


def load(path: str | os.PathLike, map_location="cpu") -> dict:
    """A checkpoint (``path``: a file, or a run folder meaning its latest)."""
    p = resolve(path)
    if not p.is_file():
        raise CheckpointError(f"{p}: no such checkpoint")
    if p.suffix.lower() == ".onnx":
        raise CheckpointError(
            f"{p}: an exported model, which trainer render, viewer and eval take; this "
            "command takes the checkpoint or run it was exported from"
        )
    try:
        import torch

        state = torch.load(p, map_location=map_location, weights_only=True)
    except Exception as exc:  # torch raises several types for a bad file
        raise CheckpointError(
            f"{p}: not a readable checkpoint ({why_unreadable(p, exc)})"
        ) from None
    missing = [k for k in REQUIRED if not isinstance(state, dict) or k not in state]
    if missing:
        raise CheckpointError(f"{p}: not a shaderball checkpoint (no {missing[0]!r})")
    return state
