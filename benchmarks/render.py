"""Render-job benchmark: seconds per frame, first vs following frames, and the share of frame
time spent outside Cycles' path tracing, in one kept-loaded Blender worker per setting.

    .venv/bin/python -m benchmarks.render            # 64²/16, 256²/64, 400²/150 (~6 min, 2 cores)
    .venv/bin/python -m benchmarks.render --quick    # 64²/16 and 128²/32 only

Per setting: one worker builds the scene; material A (procedural, 512² maps) renders sun 0
(the *first* frame: kernel load, BVH, textures) and sun 1; material B then renders suns 0-1;
A and B alternate for ``--following`` frames in all (every other following frame swaps
textures, as the farm does with 5 suns a material it would be every fifth).
"Outside path tracing" = texture upload + sky/lamp changes + Cycles sync and EXR write (render
call minus path tracing) + EXR read, over the following frames. Last, RSS is sampled over 50
materials at 64²/1 spp.
"""

from __future__ import annotations

import argparse
import statistics
import time

from benchmarks.results import Table, save
from render_jobs.materials.procedural import procedural_maps
from render_jobs.process import RenderProcess
from render_jobs.specs import RenderSettings
from render_jobs.sun import sun_from_angles

SETTINGS = [(64, 16), (256, 64), (400, 150)]
QUICK = [(64, 16), (128, 32)]
SUNS = [sun_from_angles(35, 20, 3.0), sun_from_angles(60, 250, 6.0)]


def bench(resolution: int, samples: int, following: int) -> dict:
    settings = RenderSettings(resolution=resolution, samples=samples)
    t0 = time.perf_counter()
    worker = RenderProcess(settings).start()
    startup = time.perf_counter() - t0
    materials = [procedural_maps(1, 512), procedural_maps(2, 512)]
    frames = []  # (timings, upload seconds charged to this frame)
    try:
        first = worker.render_material(materials[0], SUNS, [0, 1])
        frames += [
            (r.timings, first.material_seconds if i == 0 else 0.0)
            for i, r in enumerate(first.renders)
        ]
        k = 1
        while len(frames) < following + 1:
            r = worker.render_material(materials[k % 2], SUNS, [2 * k, 2 * k + 1])
            frames += [
                (x.timings, r.material_seconds if i == 0 else 0.0) for i, x in enumerate(r.renders)
            ]
            k += 1
    finally:
        worker.close()
    first_t, first_up = frames[0]
    rest = frames[1 : following + 1]
    total = sum(t["total"] + up for t, up in rest)
    traced = sum(t["path_tracing"] for t, _ in rest)
    return {
        "setting": f"{resolution}² / {samples} spp",
        "startup": startup,
        "first": first_t["total"] + first_up,
        "following": statistics.mean(t["total"] + up for t, up in rest),
        "outside": 1.0 - traced / total,
        "upload": sum(up for _, up in rest) / total,
        "sync": sum(t["render"] - t["path_tracing"] for t, _ in rest) / total,
        "exr": sum(t["exr_read"] for t, _ in rest) / total,
    }


def memory(materials: int = 50) -> tuple[float, float]:
    with RenderProcess(RenderSettings(resolution=64, samples=1)) as worker:
        rss = [
            worker.render_material(procedural_maps(i, 512), SUNS[:1], [i]).rss_bytes
            for i in range(materials)
        ]
    return rss[0] / 2**20, rss[-1] / 2**20


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="small settings only")
    ap.add_argument("--following", type=int, default=4, help="following frames per setting")
    args = ap.parse_args()
    rows = [bench(r, s, args.following) for r, s in (QUICK if args.quick else SETTINGS)]
    head = (
        f"{'setting':<18}{'start s':>8}{'first s':>9}{'next s':>9}{'outside PT':>11}"
        f"{'upload':>8}{'sync+write':>11}{'exr read':>9}"
    )
    print(head)
    print("-" * len(head))
    for r in rows:
        print(
            f"{r['setting']:<18}{r['startup']:>8.2f}{r['first']:>9.2f}{r['following']:>9.2f}"
            f"{r['outside']:>10.1%} {r['upload']:>7.1%} {r['sync']:>10.1%} {r['exr']:>8.1%}"
        )
    first, last = memory()
    print(f"\nRSS over 50 materials (64², 1 spp, 512² maps): {first:.0f} MB -> {last:.0f} MB")
    print(
        "outside PT = share of following-frame time not spent path tracing "
        "(target at 400²/150 spp: <= 3%)"
    )
    table = Table(
        title="Rendering: a kept-loaded Blender worker (`make bench-render`)",
        columns=["setting", "start s", "first s", "next s", "outside path tracing"],
        rows=[[r["setting"], round(r["startup"], 2), round(r["first"], 2),
               round(r["following"], 2), f"{r['outside']:.1%}"] for r in rows],  # fmt: skip
        notes=["outside path tracing: the share of a following frame's time not spent path "
               "tracing (target at 400² / 150 spp: at most 3 %)",
               f"resident memory over 50 materials (64², 1 spp, 512² maps): {first:.0f} MB "
               f"then {last:.0f} MB"],
    )  # fmt: skip
    save("render", table)


if __name__ == "__main__":
    main()
