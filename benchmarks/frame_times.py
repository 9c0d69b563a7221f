"""Frame times of the quality table's methods, in one run, without its data.

    .venv/bin/python -m benchmarks.frame_times [--resolution 128] [--spp 1,2,4,16]
        [--truth 64] [--frames 3] [--iters 20]

The quality table (``benchmarks.quality``, ``docs/quality.md``) times each method on the
day of its run. This re-times them all side by side, so their ratios come from one run on one
machine: the networks of the table (the default recipe's, the paper's U-Net with and without
skips, Zsolnai-Fehér) with fresh weights (a network's time does not depend on its weights) through
``trainer.rendering.infer.Renderer`` at batch 1 on CPU, all threads; Cycles at each ``--spp``, raw
and with OpenImageDenoise, and at ``--truth`` spp, as one kept-loaded ``RenderProcess`` a
setting, over ``--frames`` materials of the full run's test set (uniform and procedural in
turn, each under its first sun). The first frame of each Blender warms it up and is not
counted. Cycles times are whole render calls (scene changes, path tracing, denoising, EXR
out and in), as in the quality table.
"""

from __future__ import annotations

import argparse
import statistics
import time

import numpy as np
import torch

from benchmarks.quality_plan import SCALES
from benchmarks.results import Table, save
from farm.plan import JobConfig, material_specs, task_for
from render_jobs.materials import load_maps
from render_jobs.process import RenderProcess
from render_jobs.specs import RenderSettings
from trainer.model import ModelConfig
from trainer.networks import build_model
from trainer.rendering.infer import Renderer
from trainer.targets import Tonemap
from trainer.training.config import TrainConfig
from trainer.training.train import network_config


def network_ms(renderer: Renderer, maps: torch.Tensor, iters: int = 20) -> float:
    """Median ms of one frame of ``maps (1, 11, H, W) uint8`` at batch 1 (3 warm-ups)."""
    light = torch.tensor([[0.0, -0.6, 0.8, 0.3]])
    times = []
    for i in range(iters + 3):
        t0 = time.perf_counter()
        renderer.render_batch(maps, light)
        if i >= 3:
            times.append(time.perf_counter() - t0)
    return 1e3 * statistics.median(times)


def cycles_ms(settings: RenderSettings, frames: list) -> float:
    """Median ms of a whole render call with ``settings`` over ``frames`` (``(maps, sun,
    seed)`` each), in one fresh Blender; the first frame warms it up and is not counted."""

    times = []
    with RenderProcess(settings) as worker:
        for maps, sun, seed in frames:
            times.append(worker.render_material(maps, [sun], [seed]).renders[0].seconds)
    return 1e3 * statistics.median(times[1:] or times)


def sample_frames(count: int, resolution: int) -> list:
    """The first ``count`` frames of the full quality run's test set, alternating its
    uniform and procedural materials, each under its first sun: ``(maps, sun, seed)``."""

    scale = SCALES["full"]
    uniform, procedural = scale.test
    cfg = JobConfig(sources=(f"uniform:{uniform}", f"procedural:{procedural}"), out="-",
                    suns=scale.suns, resolution=resolution, seed=1)  # fmt: skip
    specs = material_specs(cfg)
    pairs = zip(range(uniform), range(uniform, uniform + procedural), strict=True)
    order = [k for pair in pairs for k in pair]
    frames = []
    for index in order[:count]:
        job = task_for(cfg, index, specs[index])
        frames.append((load_maps(job.material), job.suns[0], job.seeds[0]))
    return frames


def recipe_network(recipe: str, resolution: int) -> ModelConfig:
    """The network a ``--recipe`` trains at ``resolution``."""
    return network_config(TrainConfig(store=("-",), recipe=recipe), resolution)


def measure(args: argparse.Namespace) -> list[tuple[str, float]]:
    """``(method, ms)`` for every row, networks first."""
    r = args.resolution
    maps = torch.from_numpy(np.random.default_rng(0).integers(0, 256, (1, 11, r, r), np.uint8))
    rows = []
    for label, cfg in (
        ("ours (the default recipe)", recipe_network("shaderball", r)),
        ("the paper's U-Net", recipe_network("paper", r)),
        ("the paper's U-Net without skips", ModelConfig(r, skips=False)),
        ("Zsolnai-Fehér", ModelConfig(r, arch="zf")),
    ):
        renderer = Renderer(build_model(cfg), Tonemap(), torch.device("cpu"))
        rows.append((label, network_ms(renderer, maps, args.iters)))
        print(f"  {label}: {rows[-1][1]:.1f} ms", flush=True)
    frames = sample_frames(args.frames + 1, r)
    settings = [(f"Cycles {s} spp{' + OIDN' if d else ''}", s, d)
                for s in args.spp for d in (False, True)]  # fmt: skip
    settings.append((f"Cycles {args.truth} spp (the ground truth)", args.truth, False))
    for label, spp, denoise in settings:
        rs = RenderSettings(resolution=r, samples=spp, denoise=denoise)
        rows.append((label, cycles_ms(rs, frames)))
        print(f"  {label}: {rows[-1][1]:.1f} ms", flush=True)
    return rows


def main() -> None:
    ap = argparse.ArgumentParser(
        description=__doc__.splitlines()[0], formatter_class=argparse.RawDescriptionHelpFormatter,
        epilog="example: .venv/bin/python -m benchmarks.frame_times --spp 1,4 --frames 2",
    )  # fmt: skip
    ap.add_argument("--resolution", type=int, default=128)
    ap.add_argument("--spp", default="1,2,4,16", help="Cycles baselines, comma-separated")
    ap.add_argument("--truth", type=int, default=64, help="the ground truth's spp")
    ap.add_argument("--frames", type=int, default=3, help="timed Cycles frames a setting")
    ap.add_argument("--iters", type=int, default=20, help="timed network frames")
    args = ap.parse_args()
    try:
        args.spp = [int(v) for v in args.spp.split(",")]
    except ValueError:
        ap.error(f"--spp {args.spp!r} is not a comma-separated list of integers")
    try:
        ModelConfig(args.resolution)
    except ValueError as e:
        ap.error(f"--resolution: {e}")
    if min(args.frames, args.iters, args.truth, *args.spp) < 1:
        ap.error("--frames, --iters, --truth and every --spp must be at least 1")
    print(f"CPU, {torch.get_num_threads()} threads, {args.resolution}², batch 1:", flush=True)
    rows = measure(args)
    ours = rows[0][1]
    print("| method | ms / frame | x ours |\n|---|---|---|")
    for label, ms in rows:
        print(f"| {label} | {ms:.1f} | {ms / ours:.2f} |")
    table = Table(
        title=f"The quality table's methods timed side by side (`make bench-frames`), "
        f"{args.resolution}², batch 1",
        columns=["method", "ms / frame", "x ours"],
        rows=[[label, round(ms, 1), round(ms / ours, 2)] for label, ms in rows],
        notes=["networks with fresh weights through trainer.rendering.infer.Renderer on the "
               "CPU (all threads); Cycles: whole render calls, the first frame of each "
               "Blender not counted"],
    )  # fmt: skip
    save("frames", table)


if __name__ == "__main__":
    main()
