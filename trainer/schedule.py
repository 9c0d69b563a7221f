"""The learning rate of each step, a plain function of the global step: a resumed run
continues on the same curve, and every rank computes the same rate.

- ``constant``: ``--lr`` at every step (the paper, the authors' code);
- ``cosine``: half a cosine from ``--lr`` down to 0 over the run's steps.

Either starts with ``--warmup-steps`` of linear warm-up (``lr / warmup`` at the first step,
``lr`` at the last). The run's length is its epochs (or ``--max-steps``, when fewer) at the
ranks and batch size it starts with: a run resumed on another number of ranks has another
length, and its cosine is stretched or shrunk from the step it resumes at.
"""

from __future__ import annotations

import math

SCHEDULES = ("constant", "cosine")


def lr_at(step: int, lr: float, schedule: str, total: int, warmup: int = 0) -> float:
    """The rate of global step ``step`` (0: the first) of a run of ``total`` steps."""
    if step < warmup:
        return lr * (step + 1) / warmup
    if schedule == "constant":
        return lr
    if schedule != "cosine":
        raise ValueError(f"unknown learning-rate schedule {schedule!r}: one of {SCHEDULES}")
    span = max(total - warmup, 1)
    done = min(step - warmup, span) / span
    return lr * 0.5 * (1.0 + math.cos(math.pi * done))


def run_steps(epochs: int, max_steps: int | None, per_epoch: int) -> int:
    """The global steps of a run of ``epochs`` of ``per_epoch`` steps (``max_steps`` when
    fewer)."""
    total = epochs * per_epoch
    return total if max_steps is None else min(total, max_steps)
