"""Material reader benchmark: the time and peak memory of reading one large library material.

    .venv/bin/python -m benchmarks.materials [--texture 4096] [--repeat 2] [--no-render]
    .venv/bin/python -m benchmarks.materials --write DIR --count 12 [--layout metal-rough]

Writes one procedural material at ``--texture``² in three library layouts: a 5-panel PNG
(photo | normal | diffuse | roughness | specular), a metal-rough per-map folder of 8-bit
PNGs (base colour, OpenGL normal, roughness, metalness), and that folder with every map but
the normal at half the size (resampled by the reader). Each is read by both readers of
``render_jobs.materials.files``: ``read_svbrdf`` (float maps, 40 bytes a texel) and
``read_svbrdf_bytes`` (the 8-bit maps Blender loads, 10 bytes a texel, as a farm worker and
the viewer read them), in a fresh process per read so that its peak resident memory
(``ru_maxrss``) is that read's. Reported: seconds (best of ``--repeat``), the process's
resident memory before the read, its peak, and the maps' own size. The peak over the
resident memory before and the maps is what the reader holds for a moment.

The second table follows each bytes read into a render worker
(``render_jobs.process.RenderProcess``, as a farm worker holds one): the material is sent to
its Blender process and rendered once at 32² and 1 sample, so the time is the textures' swap
(``material_seconds``: PNGs written and loaded) and the peaks are the worker's (``ru_maxrss``)
and its Blender process's (``VmHWM``).

The materials are written by a child process too (:func:`write_apart`): on Linux a child
starts with its parent's peak, so a parent that made 4K maps would lend its children its own.
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
from PIL import Image

from benchmarks.results import Table, save
from render_jobs.materials.files import read_svbrdf, read_svbrdf_bytes
from render_jobs.materials.procedural import procedural_maps
from render_jobs.process import RenderProcess
from render_jobs.specs import RenderSettings
from render_jobs.sun import sun_from_angles

LAYOUTS = ("panel", "metal-rough", "mixed")
READERS = ("floats", "bytes")


def panel_png(folder: Path, texture: int, seed: int = 7) -> Path:
    """A 5-panel PNG of a procedural material at ``texture``² (photo, normal, diffuse,
    roughness, specular), ``folder/bench-<seed>.png``."""

    m = procedural_maps(seed, texture)
    panels = [m.diffuse, m.normal, m.diffuse, np.repeat(m.roughness, 3, 2), m.specular]
    strip = (np.concatenate(panels, 1) * 255 + 0.5).astype(np.uint8)
    path = folder / f"bench-{seed}.png"
    Image.fromarray(strip).save(path)
    return path


def metal_rough_folder(folder: Path, texture: int, seed: int = 7, mixed: bool = False) -> Path:
    """A metal-rough per-map folder of 8-bit PNGs named as ambientCG names them,
    ``folder/bench-<seed>/``; ``mixed``: all but the normal map at half the size (a set the
    reader resamples to its largest map)."""
    m = procedural_maps(seed, texture)
    out = folder / f"bench-{seed}"
    out.mkdir()
    step = 2 if mixed else 1
    maps = {"Color": m.diffuse[::step, ::step], "NormalGL": m.normal,
            "Roughness": m.roughness[::step, ::step, 0],
            "Metalness": m.roughness[::step, ::step, 0] * 0.5}  # fmt: skip
    for name, arr in maps.items():
        Image.fromarray((arr * 255 + 0.5).astype(np.uint8)).save(out / f"bench_{name}.png")
    return out


def write_one(layout: str, folder: Path, texture: int, seed: int) -> Path:
    if layout == "panel":
        return panel_png(folder, texture, seed)
    return metal_rough_folder(folder, texture, seed, mixed=layout == "mixed")


def write_apart(folder: Path, texture: int, count: int = 1, layout: str = "panel") -> list[Path]:
    """``count`` materials (seeds 0, 1, ...) in ``layout``, written by a child process so that
    this one's peak memory stays its own; their paths."""
    subprocess.run(
        [sys.executable, "-m", "benchmarks.materials", "--write", str(folder),
         "--texture", str(texture), "--count", str(count), "--layout", layout],
        check=True,
    )  # fmt: skip
    return sorted(folder.glob("bench-*"))


def resident_mb() -> float:
    """This process's resident memory (Linux ``/proc/self/statm``), MB."""
    pages = int(Path("/proc/self/statm").read_text().split()[1])
    return pages * os.sysconf("SC_PAGE_SIZE") / 2**20


def peak_mb() -> float:
    """This process's peak resident memory so far (Linux ``ru_maxrss``, KiB), MB."""
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024


def read_once(path: Path, reader: str, render: bool) -> dict:
    """Read ``path`` in this process with ``reader`` (seconds, MB resident before, peak MB,
    maps MB) and, with ``render``, render it once in a fresh render worker (texture swap
    seconds, peaks after)."""

    before = resident_mb()
    t0 = time.perf_counter()
    maps, _ = (read_svbrdf_bytes if reader == "bytes" else read_svbrdf)(path)
    seconds = time.perf_counter() - t0
    arrays = maps.arrays.values() if reader == "bytes" else (
        getattr(maps, k) for k in ("diffuse", "specular", "roughness", "normal"))  # fmt: skip
    out = {"seconds": seconds, "before_mb": before, "peak_mb": peak_mb(),
           "maps_mb": sum(a.nbytes for a in arrays) / 2**20}  # fmt: skip
    if render:
        out.update(render_once(maps))
    return out


def render_once(maps) -> dict:
    """Render ``maps`` once at 32², 1 sample, in a fresh render worker."""
    with RenderProcess(RenderSettings(resolution=32, samples=1)) as worker:
        result = worker.render_material(maps, [sun_from_angles(40, 30, 3.0)], [0])
        status = Path(f"/proc/{worker.pid}/status").read_text().splitlines()
    hwm = next(int(line.split()[1]) for line in status if line.startswith("VmHWM"))
    return {"swap_s": result.material_seconds, "worker_peak_mb": peak_mb(),
            "blender_peak_mb": hwm / 1024}  # fmt: skip


def measure(path: Path, reader: str, repeat: int, render: bool) -> dict:
    """The best of ``repeat`` reads of ``path`` by ``reader``, each in a fresh process."""
    runs = []
    for _ in range(repeat):
        cmd = [sys.executable, "-m", "benchmarks.materials", "--read", str(path),
               "--reader", reader]  # fmt: skip
        out = subprocess.run(cmd + ([] if render else ["--no-render"]),
                             capture_output=True, text=True, check=True)  # fmt: skip
        runs.append(json.loads(out.stdout.strip().splitlines()[-1]))
    return min(runs, key=lambda r: r["seconds"])


def parser() -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--texture", type=int, default=4096, help="maps' size in texels (4096)")
    ap.add_argument("--repeat", type=int, default=2, help="reads of each layout (2)")
    ap.add_argument("--no-render", dest="render", action="store_false",
                    help="reads only, no render worker (no Blender)")  # fmt: skip
    ap.add_argument("--read", type=Path, help=argparse.SUPPRESS)  # one read, as JSON
    ap.add_argument("--reader", choices=READERS, default="bytes", help=argparse.SUPPRESS)
    ap.add_argument(
        "--write",
        type=Path,
        metavar="DIR",
        help="only write --count materials in --layout into DIR (a library to try)",
    )
    ap.add_argument("--count", type=int, default=1, help="materials --write makes (1)")
    ap.add_argument(
        "--layout",
        choices=LAYOUTS,
        default="panel",
        help="what --write makes: 5-panel PNGs, metal-rough folders, or those with three "
        "maps at half size (panel)",
    )
    return ap


#: each layout's name in the tables
LAYOUT_NAMES = {"panel": "5-panel PNG", "metal-rough": "metal-rough folder (4 PNGs)",
                "mixed": "the folder, all but the normal at half size"}  # fmt: skip


def print_tables(rows: dict, texture: int, repeat: int, render: bool) -> None:
    """The reads' table of ``rows`` (a layout's name: its two readers' measures), and with
    ``render`` the render worker's."""
    print(
        f"{texture}² maps, best of {repeat} reads, each in a fresh process; "
        "floats: read_svbrdf, bytes: read_svbrdf_bytes (farm workers, the viewer)"
    )
    print(
        "| layout | read s, floats / bytes | resident MB before | peak MB, floats / bytes "
        "| maps MB, floats / bytes |"
    )
    print("|---|---|---|---|---|")
    table = Table(
        title=f"Reading one {texture}² library material (`make bench-materials`)",
        columns=["layout", "read s, floats / bytes", "resident MB before",
                 "peak MB, floats / bytes", "maps MB, floats / bytes"],
        notes=[f"best of {repeat} reads, each in a fresh process; floats: read_svbrdf, "
               "bytes: read_svbrdf_bytes (farm workers, the viewer)"],
    )  # fmt: skip
    for name, r in rows.items():
        f, b = r["floats"], r["bytes"]
        cells = [name, f"{f['seconds']:.2f} / {b['seconds']:.2f}", f"{b['before_mb']:,.0f}",
                 f"{f['peak_mb']:,.0f} / {b['peak_mb']:,.0f}",
                 f"{f['maps_mb']:,.0f} / {b['maps_mb']:,.0f}"]  # fmt: skip
        print("| " + " | ".join(cells) + " |")
        table.rows.append(cells)
    save("materials", table)
    if render:
        print("\nthe bytes read into a fresh render worker, rendered once at 32², 1 sample")
        print("| layout | texture swap s | worker peak MB | Blender process peak MB |")
        print("|---|---|---|---|")
        for name, r in rows.items():
            b = r["bytes"]
            print(f"| {name} | {b['swap_s']:.2f} | {b['worker_peak_mb']:,.0f} | "
                  f"{b['blender_peak_mb']:,.0f} |")  # fmt: skip


def main() -> None:
    ap = parser()
    args = ap.parse_args()
    if args.read is not None:
        print(json.dumps(read_once(args.read, args.reader, args.render)))
        return
    if args.texture < 8 or args.repeat < 1 or args.count < 1:
        ap.error("--texture must be at least 8, --repeat and --count at least 1")
    if args.write is not None:
        if args.write.exists() and any(args.write.glob("bench-*")):
            ap.error(f"{args.write} already holds bench-* materials")
        args.write.mkdir(parents=True, exist_ok=True)
        for seed in range(args.count):
            write_one(args.layout, args.write, args.texture, seed)
        return
    with tempfile.TemporaryDirectory() as tmp:
        rows = {}
        for layout in LAYOUTS:
            (Path(tmp) / layout).mkdir()
            path = write_apart(Path(tmp) / layout, args.texture, 1, layout)[0]
            rows[LAYOUT_NAMES[layout]] = {
                "floats": measure(path, "floats", args.repeat, False),
                "bytes": measure(path, "bytes", args.repeat, args.render),
            }
    print_tables(rows, args.texture, args.repeat, args.render)


if __name__ == "__main__":
    main()
