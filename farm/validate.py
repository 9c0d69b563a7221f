"""Reading a job's material files before anything renders: in parallel, and on resume only
those still to render.

``farm submit`` loads every file-based material it will render, with the loading code a
render worker uses, before it writes anything, so that a bad file stops the job with one line
naming it. A library material takes about a second to read at 2K and three at 4K
(docs/benchmarks.md), so a library of thousands would hold a job back for most of an hour:

- the reads go to a pool of processes, :func:`processes` of them: at most
  :data:`MAX_PROCESSES`, no more than the CPUs this process may use (its affinity and, in a
  container, its cgroup's CPU quota), since each holds up to one material (0.5 GB at 4K);
  they share those CPUs: each reads on ``CPUs // processes`` threads (``OMP_NUM_THREADS``,
  which the material reader's thread count follows), not on every CPU at once;
- a resumed job reads only the materials of shards not yet committed (:func:`pending`);
- the error raised is the first bad material's in job order, whatever order the reads end in.
"""

from __future__ import annotations

import multiprocessing
import os
from concurrent.futures import ProcessPoolExecutor

from render_jobs.cpus import omp_threads, usable_cpus
from render_jobs.materials import load_map_bytes
from shaderball.progress import bar
from storage.errors import StoreError
from storage.reader import Store
from storage.retry import StoreUnreachable

#: reading processes at most: each may hold a 4K material's files and 8-bit maps, about 0.5 GB
MAX_PROCESSES = 4


def processes(count: int) -> int:
    """Reading processes for ``count`` materials (1: read here, no pool)."""
    return max(1, min(count, MAX_PROCESSES, usable_cpus()))


def pending(cfg, layout) -> range | list[int]:
    """Indices of the materials a submit of ``cfg`` will render: those of shards not committed
    in its store, or all of them when there is no store yet or it is another job's (which the
    submit then refuses). A store out of reach (:class:`StoreUnreachable`, after its tries)
    is raised: the submit would only try it again."""

    every = range(layout.num_materials)
    try:
        store = Store(cfg.out)
        store.check_compatible(layout, cfg.dataset_settings())
        committed = set(store.committed_shards())
    except StoreUnreachable:
        raise
    except (StoreError, OSError):  # no store there yet (no bucket: the lease says so)
        return every
    return [m for s in range(layout.num_shards) if s not in committed
            for m in layout.shard_materials(s)]  # fmt: skip


class InOrder:
    """``fn`` over ``items`` by a pool of :func:`processes` processes (in this process when
    that is 1), iterated in the items' order; sized, for progress bars. ``fn`` and the items
    must pickle. An exception stops the iteration and the reads not yet started."""

    def __init__(self, fn, items):
        self.fn, self.items = fn, list(items)

    def __len__(self) -> int:
        return len(self.items)

    def __iter__(self):
        n = processes(len(self.items))
        if n == 1:
            yield from map(self.fn, self.items)
            return
        # spawn: the driver may hold threads (Ray's, tqdm's) that a fork would copy mid-step
        share = max(1, usable_cpus() // n)
        spawn = multiprocessing.get_context("spawn")
        pool = ProcessPoolExecutor(n, mp_context=spawn, initializer=_threads, initargs=(share,))
        try:
            yield from pool.map(self.fn, self.items)
        finally:
            pool.shutdown(wait=True, cancel_futures=True)


def read_all(specs: list, progress: bool = True) -> None:
    """Load every spec of ``specs`` (file-based ones) and drop the maps; raises the first bad
    one's :class:`~render_jobs.errors.MaterialError` in the order given."""
    reads = bar(InOrder(_read, specs), desc="validating", unit="material",
                disable=not progress or not specs)  # fmt: skip
    for _ in reads:
        pass


def _threads(count: int) -> None:
    """A reading process's thread share (the material reader reads ``OMP_NUM_THREADS``;
    a smaller value set already stays)."""
    given = omp_threads()
    if given is None or given > count:
        os.environ["OMP_NUM_THREADS"] = str(count)


def _read(spec) -> None:
    load_map_bytes(spec)  # the checks of load_maps, in a quarter of the memory
