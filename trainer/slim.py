"""Slimmed checkpoints: a run's network alone, small enough to carry, share and render.

A run's checkpoint keeps what resuming needs: the trained weights, their moving average when
the run keeps one, and the optimizer's two moments, all in fp32; the network that renders is a
quarter of it, or less. :func:`slimmed` keeps that one set of weights
(:func:`trainer.checkpoint.chosen`) as ``model``, its parameters in ``dtype`` (float16 by
default: 10 mantissa bits to bfloat16's 7, and trained weights sit well inside its range), its
buffers (the scene's geometry, BatchNorm's statistics) as they are, and every other entry
(config, catalog, screen UV layout, tonemap, step). Its ``slim`` entry records which set and
dtype. Loading copies the weights into the network's fp32 parameters, so a slimmed checkpoint
renders, scores, exports and starts a fine-tune (``--init``) as the whole one does, within the
rounding docs/training.md measures; a run cannot resume from it (it has no optimizer state).
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

from storage.backend import write_atomic
from trainer import checkpoint

#: the dtypes :func:`slimmed` keeps the parameters in
DTYPES = ("float16", "bfloat16", "float32")
#: the entries a run resumes from and nothing renders with
RESUME_ONLY = ("optimizer", "ema")


def parameter_names(state: dict) -> set[str]:
    """The names in the checkpoint's state dict that are the network's parameters (not its
    buffers)."""
    from trainer.model import ModelConfig
    from trainer.networks import build_model

    model = build_model(ModelConfig(**state["model_config"]))
    return {name for name, _ in model.named_parameters()}


def slimmed(state: dict, which: str = "auto", dtype: str = "float16") -> dict:
    """``state`` with the weights ``which`` names alone, their parameters cast to ``dtype``."""
    import torch

    if dtype not in DTYPES:
        raise ValueError(f"dtype must be one of {', '.join(DTYPES)}, not {dtype!r}")
    kept = checkpoint.chosen(state, which)
    cast = getattr(torch, dtype)
    params = parameter_names(state)
    model = {
        name: value.to(cast) if name in params and value.is_floating_point() else value
        for name, value in checkpoint.weights(state, kept).items()
    }
    rest = {k: v for k, v in state.items() if k not in RESUME_ONLY}
    return rest | {"model": model, "slim": {"weights": kept, "dtype": dtype}}


@dataclass(frozen=True)
class Slimmed:
    path: Path
    bytes: int
    source_bytes: int
    weights: str
    step: int


def write_slim(
    source: str | os.PathLike, output: str | os.PathLike, which: str = "auto",
    dtype: str = "float16",
) -> Slimmed:  # fmt: skip
    """Slim the checkpoint (or run folder's latest) ``source`` into ``output``, written
    atomically."""
    import torch

    found = checkpoint.resolve(source)
    state = checkpoint.load(found)
    try:
        slim = slimmed(state, which, dtype)
    except checkpoint.CheckpointError as exc:
        raise checkpoint.CheckpointError(f"{source}: {exc}") from None
    out = Path(output)
    if out.exists() and found.exists() and out.samefile(found):
        raise checkpoint.CheckpointError(f"{out}: is the checkpoint it slims; name another file")
    write_atomic(out, lambda f: torch.save(slim, f))
    return Slimmed(out, out.stat().st_size, found.stat().st_size, slim["slim"]["weights"],
                   int(state["step"]))  # fmt: skip
