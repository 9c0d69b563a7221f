"""Farm benchmark: standalone render loop vs ``farm submit`` with 1 and 2 workers, one run.

    .venv/bin/python -m benchmarks.farm [--materials 16] [--resolution 128] [--samples 32]

Standalone: one Blender worker process (1 Cycles thread), no Ray, renders the same tasks;
"standalone x2" runs two such loops at once on half the materials each: what this machine
gives two workers with no farm at all (its efficiency is the ceiling for the farm's).
Farm: the real driver (embedded Ray, 1 CPU a worker) into a fresh store each time.
Start-up = validation + Ray start + worker creation with their Blender scene builds (until
every first worker answers); frames/s counts from then to the last committed shard;
wind-down = closing the workers and stopping Ray after it. The standalone loops are timed
the same way (their Blender start is their start-up). Efficiency = frames/s ÷ (workers x
standalone frames/s).
"""

from __future__ import annotations

import argparse
import dataclasses
import shutil
import tempfile
import threading
import time

from farm.driver import submit
from farm.plan import JobConfig, material_specs, task_for
from render_jobs.materials import load_maps
from render_jobs.specs import RenderSettings
from render_jobs.worker import RenderProcess


def standalone(cfg: JobConfig, processes: int = 1) -> tuple[float, float, int]:
    """(frames/s, start-up s, frames) of plain render loops, one thread each, in ``processes``
    Blender processes at once (material i goes to loop i mod processes); no Ray."""
    specs = list(enumerate(material_specs(cfg)))
    settings = RenderSettings(resolution=cfg.resolution, samples=cfg.samples, threads=1)
    ready = threading.Barrier(processes + 1)
    frames = [0] * processes
    ends = [0.0] * processes
    t0 = time.perf_counter()

    def loop(k: int) -> None:
        with RenderProcess(settings) as worker:
            ready.wait()
            for i, spec in specs[k::processes]:
                job = task_for(cfg, i, spec)
                worker.render_material(load_maps(spec), list(job.suns), list(job.seeds))
                frames[k] += len(job.suns)
            ends[k] = time.perf_counter()  # before the Blender process is closed

    threads = [threading.Thread(target=loop, args=(k,)) for k in range(processes)]
    for t in threads:
        t.start()
    ready.wait()
    startup = time.perf_counter() - t0
    t1 = time.perf_counter()
    for t in threads:
        t.join()
    return sum(frames) / (max(ends) - t1), startup, sum(frames)


def farm(cfg: JobConfig) -> tuple[float, float, int, float]:
    """(frames/s, start-up s, frames, wind-down s) of a ``farm submit``."""
    s = submit(cfg, progress=False, echo=lambda *_: None)
    if not s.ok:
        raise RuntimeError(f"farm run failed: {s.failed_materials}")
    rate = s.frames_rendered / (s.render_end_s - s.startup_s)
    return rate, s.startup_s, s.frames_rendered, s.wall_s - s.render_end_s


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--materials", type=int, default=16)
    ap.add_argument("--resolution", type=int, default=128)
    ap.add_argument("--samples", type=int, default=32)
    args = ap.parse_args()
    root = tempfile.mkdtemp(prefix="bench-farm-")
    try:

        def cfg(workers: int, name: str) -> JobConfig:
            return JobConfig(
                sources=(f"procedural:{args.materials}",),
                out=f"{root}/{name}",
                resolution=args.resolution,
                samples=args.samples,
                shard_size=10,
                workers=workers,
                cpus_per_worker=1,
            )

        base, base_start, n = standalone(cfg(1, "x"))
        rows = [("standalone (no Ray)", 1, base, base_start, n, None, None)]
        both, both_start, n2 = standalone(cfg(2, "x"), processes=2)
        rows.append(("standalone x2 (no Ray)", 2, both, both_start, n2, None, both / (2 * base)))
        for workers, dash in ((1, True), (2, True), (2, False)):
            c = dataclasses.replace(cfg(workers, f"w{workers}{dash}"), ray_dashboard=dash)
            fps, start, frames, down = farm(c)
            name = f"farm submit, {workers} worker(s)" + ("" if dash else ", no dashboard")
            rows.append((name, workers, fps, start, frames, down, fps / (workers * base)))
    finally:
        shutil.rmtree(root, ignore_errors=True)
    print(
        f"\n{args.materials} procedural materials x 5 suns, {args.resolution}² / "
        f"{args.samples} spp, 1 CPU per worker"
    )
    head = (
        f"{'run':<40}{'workers':>8}{'frames':>8}{'frames/s':>10}{'start-up s':>12}"
        f"{'wind-down s':>13}{'efficiency':>12}"
    )
    print(head)
    print("-" * len(head))
    for name, w, fps, start, frames, down, eff in rows:
        e = f"{eff:.3f}" if eff is not None else "-"
        d = f"{down:.2f}" if down is not None else "-"
        print(f"{name:<40}{w:>8}{frames:>8}{fps:>10.3f}{start:>12.2f}{d:>13}{e:>12}")
    print("target: efficiency >= 0.97 with 2 workers")


if __name__ == "__main__":
    main()
