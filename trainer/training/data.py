"""Streaming the shard stores into training: shuffle, partition, batches.

The samples come from a :class:`storage.catalog.Catalog` split (a snapshot of the stores and
the held-out materials, kept with the run). Held-out materials are never trained on.

The order of an epoch and who reads what are pure functions of integers:

- :func:`epoch_order`: the shards permuted by ``(seed, epoch)``, their samples concatenated,
  then shuffled inside consecutive windows of ``buffer`` samples (a seekable shuffle buffer).
- :func:`rank_batches`: from a global position ``start``, global step ``g`` takes the next
  ``world * batch`` positions and rank ``r`` the ``r``-th ``batch`` of them; the last, partial
  step is split as evenly as the ranks allow. No position is read twice or skipped, and
  after ``k`` full steps exactly the first ``start + k * world * batch`` positions are read,
  whatever the world size, so a resume (even with another GPU count) continues exactly.
- :func:`worker_batches`: a rank's batch ``b`` (counted from the start of the iteration) is
  made by DataLoader worker ``b % workers``; the DataLoader's round-robin then yields them in
  order, whatever the worker count.

One iteration of a :class:`ShardStream` runs from a position to the end of the last epoch,
so the workers read the next epoch's first batches while this epoch's last ones train.
Restarting the iteration every epoch would stall each epoch's start until every worker has
read a batch, a wait that grows as epochs shorten (``benchmarks.train`` times both ways). Ranks may
end an epoch with one batch fewer; the training loop handles that with DDP's ``join``. The loader
state in a checkpoint is ``{"epoch", "position"}``.
"""

from __future__ import annotations

import os
import sys

import numpy as np
import torch
from torch.utils.data import DataLoader, IterableDataset, get_worker_info

from storage.catalog import Catalog, Split
from storage.errors import StoreError
from trainer.samples import SampleReader
from trainer.training import faults

__all__ = ["Catalog", "ShardStream", "Split", "epoch_order", "rank_batches"]

# ---- pure partition functions ---------------------------------------------------------------


def epoch_order(groups: list[np.ndarray], seed: int, epoch: int, buffer: int) -> np.ndarray:
    """The epoch's sample ids: shards (``groups``, one id array each) in a seeded order, then
    ids shuffled within windows of ``buffer``. ``(N,) int64``, a permutation of all ids."""
    if buffer < 1:
        raise ValueError(f"shuffle buffer must be at least 1, not {buffer}")
    rng = np.random.default_rng([seed, epoch])
    if not groups:
        return np.zeros(0, np.int64)
    order = np.concatenate([np.asarray(groups[i], np.int64) for i in rng.permutation(len(groups))])
    for lo in range(0, len(order), buffer):
        order[lo : lo + buffer] = rng.permutation(order[lo : lo + buffer])
    return order


def steps_left(n: int, world: int, batch: int, start: int = 0) -> int:
    """Global steps from position ``start`` to the end of an epoch of ``n`` samples."""
    return -(-max(n - start, 0) // (world * batch))


def rank_batches(n: int, world: int, rank: int, batch: int, start: int = 0) -> list[range]:
    """Rank ``rank``'s batches, as ranges of epoch positions, from position ``start`` on."""
    if not 0 <= rank < world or batch < 1 or not 0 <= start <= n:
        raise ValueError(f"bad partition n={n} world={world} rank={rank} batch={batch} {start=}")
    out = []
    step = world * batch
    full = (n - start) // step
    for g in range(full):
        lo = start + g * step + rank * batch
        out.append(range(lo, lo + batch))
    rest = (n - start) - full * step
    if rest:
        base = start + full * step
        per, extra = divmod(rest, world)  # the first `extra` ranks take one more
        lo = base + rank * per + min(rank, extra)
        size = per + (rank < extra)
        if size:
            out.append(range(lo, lo + size))
    return out


def worker_batches(num_batches: int, workers: int, worker: int) -> range:
    """The rank's batch numbers that DataLoader worker ``worker`` of ``workers`` makes."""
    return range(worker, num_batches, max(workers, 1))


class ShardStream(IterableDataset):
    """One rank's batches from a position to the end of epoch ``epochs - 1`` (or of the
    position's epoch when ``epochs`` is None), each tagged with its ``epoch``; use with
    ``batch_size=None``."""

    def __init__(
        self,
        split: Split,
        *,
        batch: int,
        seed: int,
        buffer: int,
        world: int = 1,
        rank: int = 0,
        epochs: int | None = None,
    ):
        if len(split) == 0:
            raise StoreError("no samples to stream (the split is empty)")
        self.reader = SampleReader(split)
        self.batch, self.seed, self.buffer, self.world, self.rank = batch, seed, buffer, world, rank
        self.epochs = epochs
        # (epoch, position) in shared memory, read when an iteration starts: persistent
        # DataLoader workers see a set_position made after they were started
        self._where = torch.zeros(2, dtype=torch.int64).share_memory_()

    @property
    def epoch(self) -> int:
        return int(self._where[0])

    @property
    def position(self) -> int:
        return int(self._where[1])

    def set_position(self, epoch: int, position: int) -> None:
        """Start the next iteration at global ``position`` of epoch ``epoch``."""
        self._where[0], self._where[1] = epoch, position

    def batches(self, epoch: int | None = None, position: int | None = None) -> list[np.ndarray]:
        """This rank's batches (sample ids) of ``epoch`` from ``position`` (by default the
        current epoch and position)."""
        epoch = self.epoch if epoch is None else epoch
        position = self.position if position is None else position
        order = epoch_order(self.reader.split.groups, self.seed, epoch, self.buffer)
        ranges = rank_batches(len(order), self.world, self.rank, self.batch, position)
        return [order[r.start : r.stop] for r in ranges]

    def __iter__(self):
        info = get_worker_info()
        workers, worker = (info.num_workers, info.id) if info else (1, 0)
        first, position = self.epoch, self.position
        made = 0  # batches of this iteration before this epoch's
        for epoch in range(first, first + 1 if self.epochs is None else self.epochs):
            mine = self.batches(epoch, position if epoch == first else 0)
            for b in worker_batches(len(mine), workers, (worker - made) % workers):
                yield faults.unsendable({**self.reader.batch(mine[b]), "epoch": epoch}, b)
            made += len(mine)


class Preloaded:
    """The batches of a :class:`ShardStream`, in its order, from the whole split read once into
    ``device``'s memory (``trainer train --preload``): for a store that fits there, a GPU's
    steps wait for no loader. Iterating it yields the DataLoader's batches, in its order, on
    ``device`` (with ``derive``, what that makes of them); the split is read ``chunk``
    samples at a time when it is made.

    ``derive``, if given, maps a chunk's tensors (``{"maps", "light", "render", ...}`` on
    ``device``) to the tensors each batch carries instead, computed once here: what a step
    would otherwise compute from them again every epoch. What it leaves out is not kept, so
    no batch gathers a tensor its step does not read."""

    def __init__(self, stream: ShardStream, device: torch.device, chunk: int = 256, derive=None):
        self.stream, self.device = stream, device
        reader, n = stream.reader, len(stream.reader.split)
        parts = [reader.batch(np.arange(lo, min(lo + chunk, n))) for lo in range(0, n, chunk)]
        self.data = {k: torch.cat([p[k] for p in parts]).to(device) for k in parts[0] if k != "id"}
        if derive is not None:
            made = [derive({k: v[lo : lo + chunk] for k, v in self.data.items()})
                    for lo in range(0, n, chunk)]  # fmt: skip
            self.data = {k: torch.cat([m[k] for m in made]) for k in made[0]}

    def __iter__(self):
        stream = self.stream
        first, position = stream.epoch, stream.position
        for epoch in range(first, first + 1 if stream.epochs is None else stream.epochs):
            for ids in stream.batches(epoch, position if epoch == first else 0):
                index = device_index(ids, self.device)
                batch = {k: v[index] for k, v in self.data.items()}
                yield {**batch, "id": torch.as_tensor(ids), "epoch": epoch}


def device_index(ids, device: torch.device) -> torch.Tensor:
    """``ids`` as an index on ``device``, sent without waiting for it: a copy from pageable
    host memory waits until the device has run everything queued before it, so each step's
    work would be queued only once the last step's was done; from pinned memory it is
    queued like any kernel."""
    index = torch.as_tensor(ids)
    if device.type != "cuda":
        return index.to(device)
    return index.pin_memory().to(device, non_blocking=True)


#: how DataLoader workers start: spawned, like the farm's validation pool, because a fork
#: copies the parent's threads' locks mid-use (zarr's I/O loop, tqdm's monitor, a viewer or
#: torch thread pool) and a worker can then wait forever on a lock no thread will release.
#: A spawned worker imports the trainer once, at the start of the one iteration that reads
#: every epoch.
WORKER_START = "spawn"

#: batches each DataLoader worker prepares ahead
PREFETCH = 4


def loader(stream: ShardStream, workers: int, pin_memory: bool = False) -> DataLoader:
    """The trainer's DataLoader over ``stream``: ``workers`` spawned processes (0: read in
    this process), four batches ahead each, each ending at once when it cannot send a batch
    (:func:`die_on_unsendable`)."""
    return DataLoader(
        stream,
        batch_size=None,
        num_workers=workers,
        pin_memory=pin_memory,
        prefetch_factor=PREFETCH if workers else None,
        multiprocessing_context=WORKER_START if workers else None,
        worker_init_fn=die_on_unsendable if workers else None,
    )


def die_on_unsendable(worker_id: int) -> None:  # in a DataLoader worker, before its first batch
    """Make a batch this worker cannot send end the worker.

    A worker's batches go to its rank through a ``multiprocessing`` queue, whose feeder
    thread pickles them (torch moves the tensors to ``/dev/shm`` there). When that fails (a
    full ``/dev/shm``), the queue's default prints the error and drops the batch; the rank
    then waits for it forever, or ends the epoch without it. Through the hook the queue
    offers for this (``_on_queue_feeder_error``, which ``concurrent.futures`` overrides too),
    the worker prints the error and exits, and torch's DataLoader raises in the rank
    ("DataLoader worker ... exited unexpectedly")."""
    import multiprocessing.queues
    import traceback

    def die(exc: BaseException, obj) -> None:
        traceback.print_exception(exc)
        print(f"DataLoader worker {worker_id} could not send a batch: exiting", file=sys.stderr)
        os._exit(1)

    multiprocessing.queues.Queue._on_queue_feeder_error = staticmethod(die)
