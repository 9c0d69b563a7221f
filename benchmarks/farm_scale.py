"""How far one farm driver scales: its scheduling policy, the cost of writing shards in it,
and the real driver over Ray with simulated workers.

    .venv/bin/python -m benchmarks.farm_scale [--workers 1000] [--events 20000] [--shards 40]
                                              [--sim-workers 8] [--sim-materials 400]

Three measurements of the driver process, each alone on this machine:

* **scheduling**: :class:`farm.scheduler.Scheduler` with ``--workers`` made-up workers, every
  one holding two tasks; each event is one result (``completed``) and the ``recall`` and
  ``dispatch`` that follow, as the driver loop does them. Events/s is the result rate the
  policy keeps up with.
* **commits**: real 400² results (the benchmark store's materials, ``benchmarks.trainstore``)
  through the driver's commit path: :class:`farm.assembly.ShardAssembly`, then
  ``payload_from_packed`` and ``write_shard`` into a local store (zstd + crc32c, fsync,
  commit record). Frames/s, the driver's CPU seconds a frame and stored bytes a frame.

* **simulated farm**: the real driver (``farm.driver.submit``) on a local Ray cluster of
  ``--sim-workers`` actors (:class:`SimWorker`) that answer each material at once with the
  benchmark store's real 400² results, 5 suns a material, 25 frames a shard; shards are
  written by the commit tasks (:mod:`farm.commit`). The driver's CPU seconds a frame give its
  ceiling, ``1 / (CPU s a frame)`` frames/s: over the whole run (start-up included), and at
  the margin, from a second run with a fifth of the materials (the slope, which is what a
  long job costs). The runs' own frames/s is bounded by this machine's cores, which the
  actors, the commit tasks and Ray share.
"""

from __future__ import annotations

import argparse
import os
import shutil
import tempfile
import time

import psutil
from tabulate import tabulate

from benchmarks.results import Table, save
from benchmarks.trainstore import DEFAULT, ensure_store
from farm.actor import Revocable
from farm.assembly import ShardAssembly
from farm.cluster import ray_environment
from farm.driver import submit
from farm.plan import JobConfig
from farm.scheduler import Scheduler
from render_jobs.screen_uv import ScreenUV
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
        s.recall(ids, ids, float(k))
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


class SimWorker(Revocable):
    """A render actor without Blender (the methods of ``farm.actor.RenderWorker``): each
    material's result is a stored material's real arrays, renumbered, at once."""

    store = DEFAULT  # read by each actor at start

    def __init__(self, worker_id: str, settings: dict, recycle_after: int, rss_limit_mb: int):
        super().__init__()
        self.worker_id = worker_id
        self.results = templates(Store(self.store))

    def info(self) -> dict:
        import socket

        return {"worker": self.worker_id, "pid": os.getpid(), "host": socket.gethostname(),
                "blender_pid": 0, "nice": os.getpriority(os.PRIO_PROCESS, 0)}  # fmt: skip

    def render(self, job: dict, timeout_s: float, ticket: int | None = None) -> tuple[dict, dict]:
        skipped = self.skipped(ticket, job)
        if skipped is not None:
            return skipped
        m, suns = job["material_index"], len(job["suns"])
        arrays = dict(self.results[m % len(self.results)])
        for key in ("renders", "sun_direction", "turbidity", "seed", "seconds"):
            arrays[key] = arrays[key][:suns]
        report = {"material_index": m, "seconds": arrays["seconds"].tolist(), "wall_s": 0.0,
                  "rss_mb": 0.0, "recycled": False, "geometry_hash": "", **self.info()}  # fmt: skip
        return report, arrays

    def screen_uv(self, supersample: int):
        """An empty layout of the template store's size (no Blender to render one)."""
        import numpy as np

        src = Store(self.store)
        n = src.layout.resolution * supersample
        return ScreenUV(np.zeros((n, n, 2), np.float32), np.zeros((n, n), bool),
                        src.layout.resolution, supersample,
                        src.settings.get("texture_tiling", 2.0), "simulated")  # fmt: skip

    def close(self) -> None:
        pass


def simulated(store: str, workers: int, materials: int) -> dict:
    """The real driver over a local Ray cluster of ``workers`` :class:`SimWorker` actors."""
    ray_environment("127.0.0.1")  # before Ray is imported
    from ray.cluster_utils import Cluster

    os.environ.setdefault("RAY_AUTH_MODE", "disabled")
    SimWorker.store = os.path.abspath(store)
    loopback = {"node_ip_address": "127.0.0.1", "include_dashboard": False}
    cluster = Cluster(initialize_head=True, head_node_args={"num_cpus": workers, **loopback})
    tmp = tempfile.mkdtemp(prefix="farm-sim-")
    try:
        cfg = JobConfig(sources=(f"uniform:{materials}",), out=f"{tmp}/sim.zarr", suns=5,
                        resolution=400, workers=workers, address=cluster.address,
                        ray_dashboard=False)  # fmt: skip
        me = psutil.Process()
        cpu0, t0 = sum(me.cpu_times()[:2]), time.perf_counter()
        summary = submit(cfg, progress=False, echo=lambda *_: None, actor_cls=SimWorker)
        seconds, cpu = time.perf_counter() - t0, sum(me.cpu_times()[:2]) - cpu0
        if not summary.ok:
            raise RuntimeError(f"simulated job failed: {summary}")
        frames = summary.frames_rendered
        return {"frames": frames, "fps": frames / summary.render_end_s,
                "cpu_per_frame": cpu / frames, "wall_s": seconds,
                "rss_mb": me.memory_info().rss / 2**20}  # fmt: skip
    finally:
        cluster.shutdown()
        shutil.rmtree(tmp, ignore_errors=True)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--store", default=DEFAULT)
    ap.add_argument("--workers", type=int, default=1000)
    ap.add_argument("--events", type=int, default=20000)
    ap.add_argument("--shards", type=int, default=40)
    ap.add_argument("--sim-workers", type=int, default=8)
    ap.add_argument("--sim-materials", type=int, default=400)
    args = ap.parse_args()
    if min(args.workers, args.events, args.shards, args.sim_workers, args.sim_materials) < 1:
        ap.error("--workers, --events, --shards, --sim-workers, --sim-materials must be >= 1")
    store = ensure_store(args.store)
    events_s = scheduling(args.workers, args.events)
    fps, cpu, size = commits(Store(store), args.shards)
    small = simulated(store, args.sim_workers, max(1, args.sim_materials // 5))
    sim = simulated(store, args.sim_workers, args.sim_materials)
    sim_cpu = sim["cpu_per_frame"]
    slope = (sim_cpu * sim["frames"] - small["cpu_per_frame"] * small["frames"]) / max(
        1, sim["frames"] - small["frames"]
    )
    rows = [
        (f"scheduling, {args.workers} workers x 2 tasks", f"{events_s:,.0f} results/s", "-", "-",
         "-"),
        (f"shards written in the driver, 400², {args.shards} shards, local",
         f"{fps:,.1f} frames/s", f"{cpu * 1e3:.1f}", f"{1 / cpu:,.0f}", f"{size / 1e6:.3f}"),
        (f"driver over Ray, {args.sim_workers} simulated workers, {sim['frames']} frames at "
         f"400², shards written by commit tasks", f"{sim['fps']:,.1f} frames/s",
         f"{sim_cpu * 1e3:.2f}", f"{1 / sim_cpu:,.0f}", "-"),
        (f"the same at the margin ({small['frames']} to {sim['frames']} frames)", "-",
         f"{slope * 1e3:.2f}", f"{1 / slope:,.0f}" if slope > 0 else "-", "-"),
    ]  # fmt: skip
    head = ["part of the driver", "rate here", "driver CPU ms / frame", "driver ceiling, frames/s",
            "MB stored / frame"]  # fmt: skip
    print(tabulate(rows, head, disable_numparse=True))
    print(f"driver RSS at the end of the simulated run: {sim['rss_mb']:.0f} MB")
    save("farm-scale", Table(
        title="How far one farm driver scales (`make bench-farm-scale`)",
        columns=head, rows=[list(r) for r in rows],
        notes=[f"driver resident memory at the end of the simulated run: {sim['rss_mb']:.0f} MB"],
    ))  # fmt: skip


if __name__ == "__main__":
    main()
