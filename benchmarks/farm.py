"""Farm benchmark: standalone render loop vs ``farm submit`` with 1 and 2 workers, one run.

    .venv/bin/python -m benchmarks.farm [--materials 16] [--resolution 128] [--samples 32]
                                        [--rounds 1]

Standalone: one Blender worker process (1 Cycles thread), no Ray, renders the same tasks;
"standalone x2" runs two such loops at once on half the materials each: what this machine
gives two workers with no farm at all (its efficiency is the ceiling for the farm's).
Farm: the real driver (embedded Ray, 1 CPU a worker) into a fresh store each time.
Start-up = validation + Ray start + worker creation with their Blender scene builds (until
every first worker answers); frames/s counts from then to the last committed shard;
wind-down = closing the workers and stopping Ray after it. The standalone loops are timed
the same way (their Blender start is their start-up). Efficiency = frames/s ÷ (workers x
standalone frames/s), each round against its own standalone loop. On a shared machine whose
speed drifts, ``--rounds N`` runs all rows N times in turn and prints medians, with the range
of each efficiency.
"""

from __future__ import annotations

import argparse
import dataclasses
import shutil
import statistics
import tempfile
import threading
import time

from benchmarks.results import Table, save
from farm.driver import submit
from farm.plan import JobConfig, material_specs, task_for
from render_jobs.materials import load_maps
from render_jobs.process import RenderProcess
from render_jobs.specs import RenderSettings


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


def one_round(cfg) -> list[tuple]:
    """Every row once: (name, workers, frames/s, start-up s, frames, wind-down s, efficiency),
    efficiency against this round's own standalone loop."""
    base, base_start, n = standalone(cfg(1, "x"))
    rows = [("standalone (no Ray)", 1, base, base_start, n, None, None)]
    both, both_start, n2 = standalone(cfg(2, "x"), processes=2)
    rows.append(("standalone x2 (no Ray)", 2, both, both_start, n2, None, both / (2 * base)))
    for workers, dash in ((1, True), (2, True), (2, False)):
        c = dataclasses.replace(cfg(workers, f"w{workers}{dash}"), ray_dashboard=dash)
        fps, start, frames, down = farm(c)
        name = f"farm submit, {workers} worker(s)" + ("" if dash else ", no dashboard")
        rows.append((name, workers, fps, start, frames, down, fps / (workers * base)))
        shutil.rmtree(c.out, ignore_errors=True)
    return rows


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--materials", type=int, default=16)
    ap.add_argument("--resolution", type=int, default=128)
    ap.add_argument("--samples", type=int, default=32)
    ap.add_argument(
        "--rounds",
        type=int,
        default=1,
        help="repeat every row this many times, in turn; print medians and the efficiency range",
    )
    args = ap.parse_args()
    if args.rounds < 1:
        ap.error(f"--rounds must be at least 1, not {args.rounds}")
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

        rounds = [one_round(cfg) for _ in range(args.rounds)]
    finally:
        shutil.rmtree(root, ignore_errors=True)
    print(
        f"\n{args.materials} procedural materials x 5 suns, {args.resolution}² / "
        f"{args.samples} spp, 1 CPU per worker"
        + (f"; medians of {args.rounds} rounds" if args.rounds > 1 else "")
    )
    head = (
        f"{'run':<40}{'workers':>8}{'frames':>8}{'frames/s':>10}{'start-up s':>12}"
        f"{'wind-down s':>13}{'efficiency':>12}" + (f"{'range':>14}" if args.rounds > 1 else "")
    )
    print(head)
    print("-" * len(head))
    table = Table(
        title="The farm against a standalone render loop (`make bench-farm`)",
        columns=["run", "workers", "frames", "frames/s", "start-up s", "wind-down s",
                 "efficiency", "range"],
        notes=[f"{args.materials} procedural materials x 5 suns, {args.resolution}² / "
               f"{args.samples} spp, 1 CPU a worker; medians of {args.rounds} round(s); "
               "target: efficiency at least 0.97 with 2 workers"],
    )  # fmt: skip
    for k, (name, w, *_) in enumerate(rounds[0]):
        runs = [r[k] for r in rounds]
        fps, start, frames = (statistics.median(r[i] for r in runs) for i in (2, 3, 4))
        d = "-" if runs[0][5] is None else f"{statistics.median(r[5] for r in runs):.2f}"
        effs = [r[6] for r in runs if r[6] is not None]
        e = f"{statistics.median(effs):.3f}" if effs else "-"
        spread = f"{min(effs):.3f}-{max(effs):.3f}" if effs and args.rounds > 1 else ""
        line = f"{name:<40}{w:>8}{frames:>8.0f}{fps:>10.3f}{start:>12.2f}{d:>13}{e:>12}"
        print(line + (f"{spread or '-':>14}" if args.rounds > 1 else ""))
        table.rows.append([name, w, round(frames), round(fps, 3), round(start, 2), d, e,
                           spread or None])  # fmt: skip
    print("target: efficiency >= 0.97 with 2 workers")
    save("farm", table)


if __name__ == "__main__":
    main()
