"""Viewer benchmark: the time from an edit to the new image's bytes, in three parts.

    .venv/bin/python -m benchmarks.viewer [--resolutions 128,256,400] [--frames 12]
        [--texture 1024] [--device auto] [--runtimes torch,graph,onnx] [--library N]
        [--recipes shaderball,paper] [--cache benchmarks/.cache]

For each resolution: the screen UV layout rendered by Blender at the farm's sub-sampling
(``render_jobs.screen_uv.default_supersample``; cached in ``benchmarks/.cache``), the network
of each of ``--recipes`` (``shaderball``, the default, with the layout's scene buffers for
its cues; ``paper``, width 64 with skips) with fresh weights (speed does not depend on them),
and one procedural material with ``--texture``² maps, read as the viewer reads a folder material.
Each **edit** frame changes the roughness scale, so it applies the edit to the looked-up
sub-samples of that map and filters them again (``trainer.rendering.mapping``), runs the network
(``trainer.rendering.infer.Renderer``'s inference path) and encodes a JPEG, exactly as ``trainer
viewer`` answers the page (``trainer.rendering.viewer.engine``); each **tiling edit** frame changes
the tiling, so it also looks the textures up again; each **drag** frame moves the sun (the
mapping is cached). Medians over ``--frames``; the share outside the network is (mapping +
encoding) / frame. Targets on CPU: under 6 % for an edit of values, under 20 % for a tiling
edit; on CUDA, under 1 ms outside the network. A second table gives the mapping of each
kind of value edit (:data:`EDIT_KINDS`): one map's slider at a time, or every map at once.

``--runtimes torch,onnx`` also times the same network exported (``trainer export``) and run
by ONNX Runtime on the CPU, as ``trainer viewer --checkpoint ball.onnx`` runs it
(``trainer.rendering.onnx_renderer``), row after row in one run; ``--runtimes torch,graph`` on CUDA,
the frames through the network's CUDA graph, as ``trainer viewer --cuda-graph`` runs them.

``--library N`` measures a gallery of large materials instead, at the first resolution: N
procedural ``--texture``² materials in a ``--materials`` folder, picked one after the other.
For each: its gallery picture (``trainer.rendering.viewer.app.Viewer.thumb``), its first frame (the
files read, mapped, rendered), the process's resident memory after it, which the viewer's
caches bound (``trainer.rendering.viewer.recent``), and its peak resident memory so far
(``ru_maxrss``: the caches plus what reading a material holds for a moment).
"""

from __future__ import annotations

import argparse
import statistics
import tempfile
import time
from pathlib import Path

import torch

from benchmarks.frame_times import recipe_network
from benchmarks.materials import panel_png, peak_mb, resident_mb, write_apart
from benchmarks.results import Table, save
from benchmarks.train import device_name
from render_jobs.process import RenderProcess
from render_jobs.screen_uv import ScreenUV, default_supersample
from render_jobs.specs import RenderSettings
from trainer.networks import build_model
from trainer.rendering.export import export
from trainer.rendering.infer import Renderer, pick_device
from trainer.rendering.mapping import ScreenMapper
from trainer.rendering.onnx_renderer import OnnxRenderer
from trainer.rendering.viewer.engine import Engine, Light
from trainer.rendering.viewer.materials import Edits, Library
from trainer.targets import Tonemap, light_vector, model_inputs
from trainer.training.config import RECIPES

CACHE = Path(__file__).resolve().parent / ".cache"


def layout(resolution: int, cache: Path = CACHE) -> ScreenUV:
    """The scene's screen UV layout at ``resolution`` (rendered once, then kept in ``cache``)."""
    s = default_supersample(resolution)
    path = cache / f"screen_uv-{resolution}-{s}.npz"
    if path.exists():
        return ScreenUV.from_bytes(path.read_bytes(), str(path))

    with RenderProcess(RenderSettings(resolution=resolution, samples=1)) as worker:
        suv = worker.screen_uv(s)
    cache.mkdir(parents=True, exist_ok=True)
    path.write_bytes(suv.to_bytes())
    return suv


def network(recipe: str, suv: ScreenUV):
    """The network ``recipe`` trains at the layout's resolution, fresh weights (seed 0), its
    scene buffers from the layout when its cues need them."""
    cfg = recipe_network(recipe, suv.resolution)
    torch.manual_seed(0)
    return build_model(cfg, suv.geometry if cfg.needs_geometry else None)


def library(suv: ScreenUV, count: int, texture: int, device: torch.device, tmp: Path, recipe: str):
    """Per material of a ``count``-material folder: (gallery picture s, first frame s,
    resident MB after it, peak resident MB so far)."""
    from trainer.rendering.viewer.app import Viewer

    write_apart(tmp, texture, count)  # apart: the peak column is the viewer's own
    renderer = Renderer(network(recipe, suv), Tonemap(), device)
    library = Library([], [str(tmp)], tmp / "uploads")
    engine = Engine(renderer, ScreenMapper(suv, device), library, "fresh")
    viewer = Viewer(engine, tmp / "uploads", {})
    rows = []
    try:
        for mid in library.entries:
            t0 = time.perf_counter()
            viewer.thumb(mid)
            t1 = time.perf_counter()
            engine.frame(mid, Edits(), Light())
            rows.append((t1 - t0, time.perf_counter() - t1, resident_mb(), peak_mb()))
    finally:
        viewer.close()
    return rows


def renderer_for(suv: ScreenUV, device: torch.device, runtime: str, tmp: Path, recipe: str):
    """``recipe``'s network at the layout's resolution with the same fresh weights every call:
    torch's :class:`Renderer` on ``device`` (``graph``: its frames through the CUDA graph, as
    ``trainer viewer --cuda-graph`` runs it), or (``onnx``) exported to ``tmp`` and run by
    ONNX Runtime."""
    renderer = Renderer(network(recipe, suv), Tonemap(), device, graph=runtime == "graph")
    if runtime in ("torch", "graph"):
        return renderer

    return OnnxRenderer.load(export(renderer, tmp / "net.onnx").model)


#: value edits by what moves, frame ``i`` of each (-1: the frame before): one map's slider
#: at a time, as an artist drags it, or every map at once (a preset, an undo)
EDIT_KINDS = {
    "roughness scale": lambda i: Edits(roughness_scale=0.6 + 0.01 * i),
    "diffuse tint": lambda i: Edits(roughness_scale=0.4, diffuse_tint=(1.0, 0.8 - 0.01 * i, 0.6)),
    "specular scale": lambda i: Edits(roughness_scale=0.4, specular_scale=1.5 + 0.02 * i),
    "normal strength": lambda i: Edits(roughness_scale=0.4, normal_strength=1.5 + 0.02 * i),
    "every map": lambda i: Edits(
        diffuse_scale=0.9 - 0.01 * i,
        specular_scale=1.5 + 0.02 * i,
        roughness_scale=0.5 + 0.01 * i,
        normal_strength=1.5 + 0.02 * i,
    ),
}


def measure(
    suv: ScreenUV, frames: int, texture: int, device: torch.device, tmp: Path, runtime: str,
    recipe: str,
):  # fmt: skip
    """Median milliseconds of value-edit frames (mapping, network, encoding, frame), the
    mapping of tiling-edit frames, and drag frames."""
    (tmp / "model").mkdir()  # beside the material folder, not in it
    renderer = renderer_for(suv, device, runtime, tmp / "model", recipe)
    tmp = tmp / "material"
    tmp.mkdir()
    panel_png(tmp, texture)
    library = Library([], [str(tmp)], tmp / "uploads")
    engine = Engine(renderer, ScreenMapper(suv, device), library, "fresh weights")
    mid = next(iter(library.entries))
    engine.frame(mid, Edits(roughness_scale=0.3), Light())  # warm-up: textures, grids, kernels
    engine.frame(mid, Edits(roughness_scale=0.31, tiling=1.01), Light())
    edit, tiling, drag = [], [], []
    for i in range(frames):
        f = engine.frame(mid, Edits(roughness_scale=0.4 + 0.01 * i), Light())
        assert not f.cached
        edit.append((f.mapping_ms, f.network_ms, f.encoding_ms))
    for i in range(frames):
        f = engine.frame(mid, Edits(roughness_scale=0.4, tiling=1.1 + 0.1 * i), Light())
        assert not f.cached
        tiling.append(f.mapping_ms)
    for i in range(frames):
        f = engine.frame(mid, Edits(roughness_scale=0.4), Light(azimuth=200 + 3 * i))
        assert f.cached
        drag.append(f.mapping_ms + f.network_ms + f.encoding_ms)
    kinds = {}
    for kind, edits in EDIT_KINDS.items():
        engine.frame(mid, edits(-1), Light())  # the last maps an edit of one map starts from
        ms = [engine.frame(mid, edits(i), Light()).mapping_ms for i in range(frames)]
        kinds[kind] = statistics.median(ms)
    parts = [statistics.median(x) for x in zip(*edit, strict=True)]
    retile = statistics.median(tiling)
    maps, _, _ = engine.maps(mid, Edits(roughness_scale=0.4))
    return {
        "graph_diff": graph_diff(renderer, maps) if runtime == "graph" else None,
        "kinds": kinds,
        "mapping": parts[0],
        "network": parts[1],
        "encoding": parts[2],
        "frame": statistics.median(sum(x) for x in edit),
        "outside": (parts[0] + parts[2]) / sum(parts),
        "tiling": retile,
        "tiling_outside": (retile + parts[2]) / (retile + parts[1] + parts[2]),
        "drag": statistics.median(drag),
        "supersample": suv.supersample,
        "hits": int(suv.hit.sum()),
    }


def graph_diff(renderer: Renderer, maps: torch.Tensor) -> float:
    """The largest difference of the CUDA graph's image of ``maps`` from the fp32 network's,
    in display units."""
    light = torch.from_numpy(light_vector((0.3, 0.2, 0.9), 3.0))[None]
    graphed = renderer.render_batch(maps, light)
    with torch.inference_mode():
        x = model_inputs(maps, renderer.config.roughness_channels)
        fp32 = renderer.net(x, light.to(renderer.device)).float()
    return (graphed - fp32).abs().max().item()


def print_library(suv: ScreenUV, args, device: torch.device, recipe: str) -> None:
    resolution = suv.resolution
    print(f"device: {device_name(device)}; {resolution}², {recipe}'s network; "
          f"{args.library} materials, "
          f"{args.texture}² maps (5-panel PNGs)")  # fmt: skip
    print("| material | gallery picture s | first frame s | resident MB after | peak MB so far |")
    print("|---|---|---|---|---|")
    with tempfile.TemporaryDirectory() as tmp:
        rows = library(suv, args.library, args.texture, device, Path(tmp), recipe)
        for i, (pic, first, mb, peak) in enumerate(rows):
            print(f"| {i + 1} | {pic:.2f} | {first:.2f} | {mb:,.0f} | {peak:,.0f} |", flush=True)


def parser() -> argparse.ArgumentParser:
    """The command line of ``python -m benchmarks.viewer``."""
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--resolutions", default="128,256,400")
    ap.add_argument("--frames", type=int, default=12)
    ap.add_argument("--texture", type=int, default=1024)
    ap.add_argument("--device", default="auto", choices=["auto", "cuda", "cpu"])
    ap.add_argument("--runtimes", default="torch",
                    help="what runs the network, one or more of torch, graph (torch's CUDA "
                    "graph, as trainer viewer --cuda-graph) and onnx: torch,onnx on the CPU, "
                    "torch,graph on CUDA")  # fmt: skip
    ap.add_argument("--library", type=int, default=0, metavar="N",
                    help="time a gallery of N --texture² materials (see above)")  # fmt: skip
    ap.add_argument("--cache", type=Path, default=CACHE,
                    help="where the screen UV layouts Blender renders are kept")  # fmt: skip
    ap.add_argument("--recipes", default="shaderball,paper",
                    help="whose networks to time, one or more of "
                    f"{','.join(RECIPES)} (the first for --library)")  # fmt: skip
    return ap


def checked(ap: argparse.ArgumentParser, args: argparse.Namespace):
    """The runtimes, the recipes and the device ``args`` name; a bad setting ends the
    command through ``ap.error`` (one line, exit 2) before anything runs."""
    if args.frames < 1:
        ap.error("--frames must be at least 1")
    if args.library < 0:
        ap.error("--library must be 0 or more")
    runtimes = args.runtimes.split(",")
    recipes = args.recipes.split(",")
    if not set(recipes) <= set(RECIPES):
        ap.error(f"--recipes {args.recipes!r}: one or more of {', '.join(RECIPES)}")
    if not set(runtimes) <= {"torch", "graph", "onnx"}:
        ap.error(f"--runtimes {args.runtimes!r}: one or more of torch, graph, onnx")
    device = pick_device(args.device)
    if "onnx" in runtimes and device.type != "cpu":
        ap.error("--runtimes onnx runs on the CPU: add --device cpu")
    if "graph" in runtimes and device.type != "cuda":
        ap.error("--runtimes graph runs on CUDA: add --device cuda")
    return runtimes, recipes, device


def edit_table(args: argparse.Namespace, device: torch.device) -> Table:
    """The saved table of the edit and drag frames, with no rows yet."""
    return Table(
        title=f"The viewer: an edit's time (`make bench-viewer`), texture {args.texture}², "
        f"medians of {args.frames} frames",
        columns=["resolution", "network", "runtime", "sub-samples", "mapping ms", "network ms",
                 "encoding ms", "edit frame ms", "outside the network", "drag frame ms"],
        machine=device_name(device),
        notes=[
            "networks with fresh weights: shaderball is the default recipe's (its width, its "
            "scene cues computed every frame), paper the paper's (width 64); an edit frame "
            "changes a map's scale (mapping from the kept sub-samples, the network, the JPEG); "
            "a drag frame moves the sun"
        ],
    )  # fmt: skip


def print_row(r: int, recipe: str, runtime: str, m: dict) -> None:
    """One measured network's line of the printed table."""
    print(
        f"| {r}² | {recipe} | {runtime} | {m['supersample']}² ({m['hits']:,} hits) | "
        f"{m['mapping']:.1f} | "
        f"{m['network']:.2f} | {m['encoding']:.2f} | {m['frame']:.1f} | "
        f"{100 * m['outside']:.1f} % | {m['tiling']:.1f} | "
        f"{100 * m['tiling_outside']:.1f} % | {m['drag']:.1f} |",
        flush=True,
    )


def main() -> None:
    ap = parser()
    args = ap.parse_args()
    runtimes, recipes, device = checked(ap, args)
    if args.library:
        first = layout(int(args.resolutions.split(",")[0]), args.cache)
        return print_library(first, args, device, recipes[0])
    print(f"device: {device_name(device)}; torch threads {torch.get_num_threads()}; "
          f"texture {args.texture}²; medians of {args.frames} frames")  # fmt: skip
    print(
        "| resolution | network | runtime | sub-samples | mapping ms | network ms | encoding ms "
        "| edit frame ms | outside the network | tiling edit: mapping ms | outside the network "
        "| drag frame ms |"
    )
    print("|---|---|---|---|---|---|---|---|---|---|---|---|")
    table = edit_table(args, device)
    by_kind = []
    with tempfile.TemporaryDirectory() as tmp:
        for r, recipe, runtime in (
            (int(v), n, t) for v in args.resolutions.split(",") for n in recipes for t in runtimes
        ):
            sub = Path(tmp) / f"{r}-{recipe}-{runtime}"
            sub.mkdir()
            m = measure(
                layout(r, args.cache), args.frames, args.texture, device, sub, runtime, recipe
            )
            by_kind.append((r, f"{recipe}, {runtime}", m))
            print_row(r, recipe, runtime, m)
            table.rows.append([
                f"{r}²", recipe, runtime, f"{m['supersample']}²", round(m["mapping"], 1),
                round(m["network"], 2), round(m["encoding"], 2), round(m["frame"], 1),
                f"{100 * m['outside']:.1f} %", round(m["drag"], 1),
            ])  # fmt: skip
    for r, kind, m in by_kind:
        if m["graph_diff"] is not None:
            line = f"{r}², {kind}: max |diff| from fp32 {m['graph_diff']:.4f}"
            print(line)
            table.notes.append(line)
    print_kinds(by_kind)
    save(f"viewer-{device.type}", table)


def print_kinds(rows) -> None:
    """Each kind of value edit's mapping ms and share outside the network (mapping +
    encoding, against the network and encoding of the edit frames above)."""
    print("\nvalue edits by what moves: mapping ms (outside the network)")
    print("| resolution | network, runtime | " + " | ".join(EDIT_KINDS) + " |")
    print("|---|---|" + "---|" * len(EDIT_KINDS))
    for r, runtime, m in rows:
        rest = m["network"] + m["encoding"]
        cells = [
            f"{ms:.2f} ({100 * (ms + m['encoding']) / (ms + rest):.1f} %)"
            for ms in m["kinds"].values()
        ]
        print(f"| {r}² | {runtime} | " + " | ".join(cells) + " |")


if __name__ == "__main__":
    main()
