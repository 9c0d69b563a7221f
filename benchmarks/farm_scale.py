"""How far one farm driver scales: its scheduling policy and its shard commits, without Ray.

    .venv/bin/python -m benchmarks.farm_scale [--workers 1000] [--events 20000] [--shards 40]

Two ceilings of the driver process, each measured alone on this machine:

* **scheduling**: :class:`farm.scheduler.Scheduler` with ``--workers`` made-up workers, every
  one holding two tasks; each event is one result (``completed``) and the ``dispatch`` that
  follows, as the driver loop does it. Events/s is the result rate the policy keeps up with.
* **commits**: real 400² results (the benchmark store's materials, ``benchmarks.trainstore``)
  through the driver's commit path: :class:`farm.assembly.ShardAssembly`, then
  ``payload_from_packed`` and ``write_shard`` into a local store (zstd + crc32c, fsync,
  commit record). Frames/s, the driver's CPU seconds a frame and stored bytes a frame.

Not measured here: Ray's own cost per result (``ray.wait`` / ``ray.get`` of a 3.6 MB result),
which a simulated farm on a Ray cluster would add.
"""

from __future__ import annotations

import argparse
import shutil
import tempfile
import time

import psutil
from tabulate import tabulate

from benchmarks.trainstore import DEFAULT, ensure_store
from farm.assembly import ShardAssembly
from farm.scheduler import Scheduler
from storage.convert import payload_from_packed
from storage.reader import Store
from storage.schema import Layout
from storage.writer import create_store, write_shard


def scheduling(workers: int, events: int) -> float:
    """Results a second the scheduling policy handles with ``workers`` busy workers."""
    ids = [f"w{i}" for i in range(workers)]
    s = Scheduler(range(events + 2 * workers + 1), backoff_s=1.0)
    s.dispatch(ids, ids, 0.0)
    t0 = time.perf_counter()
    for k in range(events):
        w = ids[k % workers]
        s.completed(w, s.running(w), float(k))
        s.dispatch(ids, ids, float(k))
    return events / (time.perf_counter() - t0)


def templates(store: Store) -> list[dict]:
    """Each stored material as a worker's packed result (``storage.convert.pack_material``)."""
    out = []
    for shard in store.committed_shards():
        p = store.read_shard(shard)
        k = store.layout.suns_per_material
        for j in range(len(p.maps)):
            rows = slice(j * k, (j + 1) * k)
            out.append(
                {
                    "maps": p.maps[j],
                    "renders": p.renders[rows],
                    "sun_direction": p.sun_direction[rows],
                    "turbidity": p.turbidity[rows],
                    "seed": p.seed[rows],
                    "seconds": p.render_seconds[rows],
                }
            )
    return out


def commits(src: Store, shards: int) -> tuple[float, float, float]:
    """(frames/s, driver CPU s a frame, stored bytes a frame) of the commit path."""
    results = templates(src)
    lay = src.layout
    layout = Layout(
        shards * lay.materials_per_shard, lay.suns_per_material, lay.resolution, lay.shard_size
    )
    tmp = tempfile.mkdtemp(prefix="farm-scale-")
    try:
        store = create_store(f"{tmp}/s.zarr", layout, {})
        assembly = ShardAssembly(layout)
        record = {"kind": "uniform", "source_id": "bench", "spec": {}}
        me = psutil.Process()
        cpu0, t0 = sum(me.cpu_times()[:2]), time.perf_counter()
        for m in range(layout.num_materials):
            whole = assembly.add(m, results[m % len(results)])
            if whole is not None:
                shard, packed = whole
                records = [record] * len(packed)
                write_shard(store, shard, payload_from_packed(layout, shard, packed, records))
        seconds, cpu = time.perf_counter() - t0, sum(me.cpu_times()[:2]) - cpu0
        size = sum(
            store.backend.size(k) or 0
            for s in range(layout.num_shards)
            for k in store.shard_keys(s)
        )
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    frames = layout.num_samples
    return frames / seconds, cpu / frames, size / frames


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--store", default=DEFAULT)
    ap.add_argument("--workers", type=int, default=1000)
    ap.add_argument("--events", type=int, default=20000)
    ap.add_argument("--shards", type=int, default=40)
    args = ap.parse_args()
    if min(args.workers, args.events, args.shards) < 1:
        ap.error("--workers, --events and --shards must be at least 1")
    events_s = scheduling(args.workers, args.events)
    fps, cpu, size = commits(Store(ensure_store(args.store)), args.shards)
    rows = [
        (f"scheduling, {args.workers} workers x 2 tasks", f"{events_s:,.0f} results/s", "-", "-"),
        (f"commits at 400², {args.shards} shards, local", f"{fps:,.1f} frames/s",
         f"{cpu * 1e3:.1f}", f"{size / 1e6:.3f}"),
    ]  # fmt: skip
    head = ["part of the driver", "rate", "CPU ms / frame", "MB stored / frame"]
    print(tabulate(rows, head, disable_numparse=True))


if __name__ == "__main__":
    main()
