"""Blender start in a farm worker: seconds to ready and the Blender process's memory.

    .venv/bin/python -m benchmarks.worker_start [--starts 5] [--resolution 128]

A farm worker is a Ray actor holding a ``RenderProcess``, whose Blender child starts with the
actor and again at each recycle. This starts Blender ``--starts`` times each way in one Ray
actor on the farm's embedded Ray, the two ways taking turns:

- ``RenderProcess`` as the farm runs it: the child spawned without its parent's main script;
- spawned as ``multiprocessing`` does by default: the parent's main script, in a Ray actor
  Ray's ``default_worker.py``, run again in the child, which so imports Ray before ``bpy``.

Per way: the median and range of the seconds from ``start()`` to the child's ready message
(Blender loaded and the scene built), the child's resident memory then (``VmRSS``), and
whether it had Ray's ``_raylet`` mapped.
"""

from __future__ import annotations

import argparse
import contextlib
import statistics
import time

import render_jobs.process as rp
from farm.cluster import connect, ray_environment
from render_jobs.specs import RenderSettings

WAYS = {
    "RenderProcess (the parent's main script not run again)": False,
    "multiprocessing's default spawn (Ray's worker script run again)": True,
}


class Starter:
    """The actor: starts one Blender at a time and reports on it."""

    def start(self, resolution: int, default_spawn: bool) -> dict:
        hidden = rp._parent_main_hidden  # the one step this benchmark takes away
        if default_spawn:
            rp._parent_main_hidden = contextlib.nullcontext
        try:
            t0 = time.perf_counter()
            worker = rp.RenderProcess(RenderSettings(resolution=resolution, threads=1)).start()
            seconds = time.perf_counter() - t0
        finally:
            rp._parent_main_hidden = hidden
        try:
            with open(f"/proc/{worker.pid}/status") as f:
                rss = next(int(line.split()[1]) for line in f if line.startswith("VmRSS"))
            with open(f"/proc/{worker.pid}/maps") as f:
                ray_mapped = "_raylet" in f.read()
        finally:
            worker.close()
        return {"seconds": seconds, "rss_mb": rss / 1024, "ray": ray_mapped}


def measure(starts: int, resolution: int) -> dict[str, list[dict]]:
    """``starts`` Blender starts each way, taking turns, in one actor on the farm's embedded
    Ray (or the cluster ``RAY_ADDRESS`` names), started as ``farm submit`` starts it."""

    ray_environment(None)
    import ray

    connect(None, dashboard=False)
    try:
        actor = ray.remote(num_cpus=1)(Starter).remote()
        rows: dict[str, list[dict]] = {way: [] for way in WAYS}
        for _ in range(starts):
            for way, default_spawn in WAYS.items():
                rows[way].append(ray.get(actor.start.remote(resolution, default_spawn)))
        return rows
    finally:
        ray.shutdown()


def print_table(rows: dict[str, list[dict]], resolution: int) -> None:
    starts = len(next(iter(rows.values())))
    print(f"Blender starts in one Ray actor, {starts} each way, {resolution}² scene")
    print("| spawned | start s, median (range) | resident MB, median | Ray in Blender |")
    print("|---|---|---|---|")
    for way, runs in rows.items():
        s = [r["seconds"] for r in runs]
        rss = statistics.median(r["rss_mb"] for r in runs)
        ray_in = {0: "no", len(runs): "yes"}.get(sum(r["ray"] for r in runs), "some")
        span = f"{statistics.median(s):.2f} ({min(s):.2f}-{max(s):.2f})"
        print(f"| {way} | {span} | {rss:.0f} | {ray_in} |")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--starts", type=int, default=5, help="Blender starts each way (default 5)")
    ap.add_argument("--resolution", type=int, default=128, help="the scene's side in pixels")
    args = ap.parse_args()
    if args.starts < 1:
        ap.error(f"--starts {args.starts}: must be at least 1")
    if args.resolution < 16:
        ap.error(f"--resolution {args.resolution}: must be at least 16")
    print_table(measure(args.starts, args.resolution), args.resolution)


if __name__ == "__main__":
    main()
