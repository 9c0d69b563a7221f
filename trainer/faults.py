"""Fault injection for the trainer's tests: a rank that dies mid-run.

``SHADERBALL_TRAIN_CRASH_AT=N``: rank 0 of a first torchrun attempt exits abruptly
(``os._exit(3)``, as a killed process would, with nothing flushed) right after its ``N``-th
optimizer step of the run, counted from step 0 across resumes; torchrun then restarts every
rank. Unset (production), :func:`install` does nothing.
"""

from __future__ import annotations

import itertools
import os

import torch

CRASH_ENV = "SHADERBALL_TRAIN_CRASH_AT"


def install(opt: torch.optim.Optimizer, step: int, master: bool) -> None:
    """Arm the crash on ``opt`` (now at global ``step``) if the environment asks for it."""
    at = int(os.environ.get(CRASH_ENV, "0") or 0)
    first_attempt = os.environ.get("TORCHELASTIC_RESTART_COUNT") == "0"
    if not at or not master or not first_attempt:
        return
    steps = itertools.count(step + 1)

    def crash_after(optimizer, args, kwargs) -> None:
        if next(steps) == at:
            os._exit(3)

    opt.register_step_post_hook(crash_after)
