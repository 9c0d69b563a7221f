"""Shared memory for the DataLoader's batches, checked before training starts.

A DataLoader worker hands each batch to its rank through shared memory (a file in
``/dev/shm``). A container's ``/dev/shm`` is small unless it is given one (64 MB under Docker
and in a Kubernetes pod without an ``emptyDir`` of ``medium: Memory`` there), and a worker
that cannot write a batch there cannot send it. So ``trainer launch`` and a lone
``trainer train`` compare the space the loaders of every rank on the node can hold at once
with what ``/dev/shm`` has free, and stop before any rank starts when it is short. A worker
that cannot send a batch all the same exits (:func:`trainer.training.data.die_on_unsendable`), which
stops the run.
"""

from __future__ import annotations

import shutil
from pathlib import Path

from shaderball.cli import human_bytes
from storage.schema import PACKED_CHANNELS
from trainer.training.data import PREFETCH

SHM = Path("/dev/shm")


def batch_bytes(resolution: int, batch: int) -> int:
    """One batch as the loader sends it (:meth:`trainer.training.data.SampleReader.batch`): the
    packed
    uint8 map channels and 3 float16 render channels a pixel, 4 float32 light values and an
    int64 id a sample."""
    return batch * (resolution * resolution * (PACKED_CHANNELS + 3 * 2) + 4 * 4 + 8)


def loader_bytes(resolution: int, batch: int, workers: int, ranks: int) -> int:
    """The most the loaders of ``ranks`` ranks hold in shared memory at once: each of a
    rank's ``workers`` keeps :data:`PREFETCH` batches in flight, and the rank holds the one it
    trains on."""
    if workers == 0:
        return 0
    return ranks * (workers * PREFETCH + 1) * batch_bytes(resolution, batch)


def shortfall(need: int, ranks: int, workers: int, free: int, where: Path = SHM) -> str | None:
    """Why ``free`` bytes of shared memory in ``where`` are too few for ``need``, in one line
    (None when they are enough)."""
    if need <= free:
        return None
    return (
        f"{where} has {human_bytes(free)} free, and the data loaders of {ranks} rank(s) hold up "
        f"to {human_bytes(need)} of batches there ({workers} worker(s) a rank, "
        f"{PREFETCH} batches ahead each): give the container a larger {where} (Kubernetes: an "
        "emptyDir with medium Memory mounted there; Docker: --shm-size), or lower --workers "
        "(0 reads in the rank's own process) or --batch-size"
    )


def check(resolution: int, batch: int, workers: int, ranks: int, where: Path = SHM) -> str | None:
    """:func:`shortfall` for ``where`` (None where it is not a folder, as on macOS)."""
    if not where.is_dir():
        return None
    need = loader_bytes(resolution, batch, workers, ranks)
    return shortfall(need, ranks, workers, shutil.disk_usage(where).free, where)
