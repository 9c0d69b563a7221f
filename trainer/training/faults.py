"""Fault injection for the trainer's tests: a rank that dies mid-run, a lost batch.

``SHADERBALL_TRAIN_CRASH_AT=N``: rank 0 of a first torchrun attempt exits abruptly
(``os._exit(3)``, as a killed process would, with nothing flushed) right after its ``N``-th
optimizer step of the run, counted from step 0 across resumes; torchrun then restarts every
rank. Unset (production), :func:`install` does nothing.

``SHADERBALL_TRAIN_UNSENDABLE=K``: a DataLoader worker cannot send the batch numbered ``K``
(from 0) of each epoch's batches on its rank, as when ``/dev/shm`` is full: the batch holds
a value that cannot be pickled, so the worker's queue thread fails to send it
(:func:`trainer.training.data.die_on_unsendable`). Unset, :func:`unsendable` returns its batch as it
is.
"""

from __future__ import annotations

import itertools
import os
import threading

import torch
from torch.utils.data import get_worker_info

CRASH_ENV = "SHADERBALL_TRAIN_CRASH_AT"
UNSENDABLE_ENV = "SHADERBALL_TRAIN_UNSENDABLE"


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


def unsendable(batch: dict, number: int) -> dict:
    """``batch``, the ``number``-th of its epoch on its rank, made unsendable by a DataLoader
    worker if the environment asks for it."""
    at = os.environ.get(UNSENDABLE_ENV)
    if at is None or int(at) != number or get_worker_info() is None:
        return batch
    return {**batch, "unsendable": threading.Lock()}
