"""The learning rate of each step, a plain function of the global step: a resumed run
continues on the same curve, and every rank computes the same rate.

- ``constant``: ``--lr`` at every step (the paper, the authors' code);
- ``cosine``: half a cosine from ``--lr`` down to 0 over the run's steps;
- ``onecycle``: Smith's one-cycle policy as torch's ``OneCycleLR`` draws it by default: the
  rate rises along half a cosine from ``lr / 25`` to ``lr`` over the first 30 % of the run,
  then falls along half a cosine to 0 (OIDN trains so).

``constant`` and ``cosine`` start with ``--warmup-steps`` of linear warm-up (``lr / warmup``
at the first step, ``lr`` at the last); ``onecycle``'s rise is its warm-up. The run's length
is its epochs (or ``--max-steps``, when fewer) at the ranks and batch size it runs with. The
falling cosine runs from its *knee* ``(step, scale)``, where the rate is ``scale x lr``, down
to 0 at the run's last step; a run starts with the knee at the end of its warm-up (or rise),
scale 1. A run resumed with another length (other epochs,
``--max-steps``, rank count or batch size) moves the knee to the step it resumes at, with the
rate it had there (:func:`resumed_knee`): the rate goes on from where it was, without a jump,
down to 0 at the new end. Checkpoints keep the knee and the length (``record``).
"""

from __future__ import annotations

import math

SCHEDULES = ("constant", "cosine", "onecycle")
#: the schedules that fall to 0 at the run's end, from their knee
DECAYING = ("cosine", "onecycle")
#: the share of a one-cycle run spent rising, and where the rise starts (``lr / 25``)
ONECYCLE_RISE = 0.3
ONECYCLE_START = 1 / 25

Knee = tuple[int, float]


def lr_at(
    step: int, lr: float, schedule: str, total: int, warmup: int = 0, knee: Knee | None = None
) -> float:
    """The rate of global step ``step`` (0: the first) of a run of ``total`` steps whose
    cosine starts at ``knee`` (default: the end of the warm-up, at ``lr``)."""
    if schedule not in SCHEDULES:
        raise ValueError(f"unknown learning-rate schedule {schedule!r}: one of {SCHEDULES}")
    if schedule == "onecycle":
        knee = knee if knee is not None else first_knee(schedule, total, warmup)
        if step < knee[0]:
            rise = 0.5 * (1 - math.cos(math.pi * (step + 1) / knee[0]))
            return lr * (ONECYCLE_START + (1 - ONECYCLE_START) * rise)
    elif step < warmup:
        return lr * (step + 1) / warmup
    if schedule == "constant":
        return lr
    start, scale = knee if knee is not None else (warmup, 1.0)
    span = max(total - start, 1)
    done = min(max(step - start, 0), span) / span
    return lr * scale * 0.5 * (1.0 + math.cos(math.pi * done))


def run_steps(epochs: int, max_steps: int | None, per_epoch: int) -> int:
    """The global steps of a run of ``epochs`` of ``per_epoch`` steps (``max_steps`` when
    fewer)."""
    total = epochs * per_epoch
    return total if max_steps is None else min(total, max_steps)


def first_knee(schedule: str, total: int, warmup: int) -> Knee:
    """Where a fresh run's falling half-cosine starts: after the warm-up, or after the
    one-cycle rise."""
    if schedule == "onecycle":
        return (max(1, round(ONECYCLE_RISE * total)), 1.0)
    return (warmup, 1.0)


def record(schedule: str, total: int, knee: Knee) -> dict:
    """What a checkpoint keeps of the schedule, for :func:`resumed_knee`."""
    return {"schedule": schedule, "total": total, "knee": [knee[0], knee[1]]}


def resumed_knee(
    step: int, was: dict | None, total: int, warmup: int, schedule: str = "cosine"
) -> Knee:
    """The knee of a run resumed at ``step`` with ``total`` steps, from its checkpoint's
    :func:`record` ``was``: the same knee when the length is the same (the same rates as the
    run never stopped) or the cosine has not begun; else ``step``, at the rate the run had
    there, which is 0 for a cosine that had ended. A run that was constant starts its cosine
    at ``step`` (or at the end of the warm-up, if later), at ``lr``. A checkpoint with no
    record gets the knee of a run of ``schedule`` that started with the new length. A
    one-cycle run resumed in its rise keeps its knee, so its rise ends where it would have."""
    if was is None:
        return first_knee(schedule, total, warmup)
    if was["schedule"] not in DECAYING:
        return (max(step, warmup), 1.0)
    knee = (int(was["knee"][0]), float(was["knee"][1]))
    if total == was["total"] or step <= knee[0]:
        return knee
    return (step, lr_at(step, 1.0, was["schedule"], was["total"], warmup, knee))
