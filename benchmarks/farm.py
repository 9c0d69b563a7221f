"""Farm benchmark: standalone render loop vs ``farm submit`` with 1 and 2 workers, one run.

    .venv/bin/python -m benchmarks.farm [--materials 16] [--resolution 128] [--samples 32]

Standalone: one Blender worker process (1 Cycles thread), no Ray, renders the same tasks.
Farm: the real driver (embedded Ray, 1 CPU a worker) into a fresh store each time.
frames/s of the farm counts the render phase (after Ray start and worker creation; the
workers' Blender scene builds are inside it). Efficiency = farm frames/s ÷ (workers ×
standalone frames/s). Start-up = validation + Ray start + worker creation.
"""

from __future__ import annotations

import argparse
import shutil
import tempfile
import time

from farm.driver import submit
from farm.plan import JobConfig, material_specs, task_for
from render_jobs.materials import load_maps
from render_jobs.specs import RenderSettings
from render_jobs.worker import RenderProcess


def standalone(cfg: JobConfig) -> tuple[float, float, int]:
    """(frames/s, start-up s, frames) of a plain render loop on one thread."""
    t0 = time.perf_counter()
    settings = RenderSettings(resolution=cfg.resolution, samples=cfg.samples, threads=1)
    with RenderProcess(settings) as worker:
        startup = time.perf_counter() - t0
        t1 = time.perf_counter()
        frames = 0
        for i, spec in enumerate(material_specs(cfg)):
            job = task_for(cfg, i, spec)
            worker.render_material(load_maps(spec), list(job.suns), list(job.seeds))
            frames += len(job.suns)
        return frames / (time.perf_counter() - t1), startup, frames


def farm(cfg: JobConfig) -> tuple[float, float, int]:
    s = submit(cfg, progress=False, echo=lambda *_: None)
    if not s.ok:
        raise RuntimeError(f"farm run failed: {s.failed_materials}")
    return s.frames_rendered / (s.wall_s - s.startup_s), s.startup_s, s.frames_rendered


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
        rows = [("standalone (no Ray)", 1, base, base_start, n, None)]
        for workers in (1, 2):
            fps, start, frames = farm(cfg(workers, f"w{workers}"))
            rows.append(
                (
                    f"farm submit, {workers} worker(s)",
                    workers,
                    fps,
                    start,
                    frames,
                    fps / (workers * base),
                )
            )
    finally:
        shutil.rmtree(root, ignore_errors=True)
    print(
        f"\n{args.materials} procedural materials x 5 suns, {args.resolution}² / "
        f"{args.samples} spp, 1 CPU per worker"
    )
    head = (
        f"{'run':<26}{'workers':>8}{'frames':>8}{'frames/s':>10}{'start-up s':>12}"
        f"{'efficiency':>12}"
    )
    print(head)
    print("-" * len(head))
    for name, w, fps, start, frames, eff in rows:
        e = f"{eff:.3f}" if eff is not None else "-"
        print(f"{name:<26}{w:>8}{frames:>8}{fps:>10.3f}{start:>12.2f}{e:>12}")
    print("target: efficiency >= 0.97 with 2 workers")


if __name__ == "__main__":
    main()
