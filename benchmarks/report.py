"""The benchmarks page: every table in ``benchmarks/results/`` rendered into
``docs/benchmarks.md``, each with the command, machine and date that made it.

    python -m benchmarks.report            # writes docs/benchmarks.md
    python -m benchmarks.report --check    # exit 1 when the page is not the tables' own

Each benchmark writes its table when it runs (:mod:`benchmarks.results`); run this after, and
commit both. Sections follow :data:`SECTIONS`; a table in no section comes last.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from benchmarks.results import FOLDER, load

PAGE = Path(__file__).resolve().parent.parent / "docs" / "benchmarks.md"

#: (heading, the result names in it, in order)
SECTIONS = (
    ("What the network learns per image pass", (
        "learning-64-16k", "learning-64-16k-more", "learning-64-64k", "learning-64-64k-more",
        "learning-64-noise", "learning-64-noise-more", "learning-128-8k",
        "learning-64-b128-default-none", "learning-64-b128-default-sqrt",
        "learning-64-b128-default-bf16", "learning-64-b128-default-128k",
        "learning-64-b128-default-384k", "learning-64-b128-default-1470k",
        "learning-64-700-b128-default-384k", "learning-64-800-b128-default-384k",
        "learning-64-800-b128-default-768k", "learning-64-800-b128-default-128k",
        "learning-64-1100-b128-default-128k", "learning-64-1100-b128-default-384k",
        "learning-64-1100-b128-default-768k",
        "learning-64-100-b128-wd-128k",
        "learning-64-b128-paper-none", "learning-64-b128-paper-sqrt", "learning-64-b128-paper-384k",
        "learning-64-b128-paper-1470k",
        "learning-gpu",
    )),  # fmt: skip
    ("Training", (
        "pass-flops", "cpu-train-64", "cpu-train-128", "cpu-train-64-avx512-bf16",
        "cpu-train-128-avx512-bf16", "train-cpu", "train-cuda",
    )),  # fmt: skip
    ("Inference", ("infer-cpu", "infer-cuda", "frames")),
    ("The viewer", ("viewer-cpu", "viewer-cuda")),
    ("Rendering and the farm", ("render", "farm", "farm-scale", "materials")),
    ("Storage and the dashboard", ("storage", "render-bits", "dashboard")),
)  # fmt: skip

INTRO = """# Benchmarks

Every table below is written by its benchmark (`benchmarks/results/NAME.json`) and this page
by `python -m benchmarks.report`; a table states the command, the machine and the date that
made it. Speed and memory targets live here, never in the tests. The machines are shared
and noisy: compare rows of one table (one run), not figures across tables.

| command | what it measures |
|---|---|
| `make bench-learning` | held-out scores per recipe for a budget of passes; the truth's noise |
| `make bench-flops` | the FLOPs of a training image pass, per recipe and resolution |
| `make bench-train` | training images/s and data wait at 400² |
| `make bench-infer` | ms a frame at batch 1, frames/s batched (CUDA: bf16, CUDA graphs) |
| `make bench-frames` | the quality table's methods timed side by side: networks and Cycles |
| `make bench-viewer` | the viewer: an edit's mapping, network and encoding ms |
| `make bench-render` | a kept-loaded Blender worker: frames, time outside path tracing |
| `make bench-farm` | the farm against a standalone render loop: frames/s and efficiency |
| `make bench-farm-scale` | one driver's ceilings: scheduling, commits, a simulated farm |
| `make bench-materials` | reading a 4K library material: seconds and peak memory |
| `make bench-storage` | bytes a sample, write MB/s and reads/s against MDS and WebDataset |
| `make bench-dashboard` | the dashboard's pages and `/metrics` with 1 to 1,000 stores |

On a GPU machine with CUDA torch and no package registry, `bash benchmarks/gpu.sh
learn|train|infer|viewer` runs the CUDA rows: `make gpu-stores gpu-wheels` here puts the
stores and wheels in place to carry (docs/development.md, "On a GPU").
"""


def render(folder: Path = FOLDER) -> str:
    tables = {p.stem: load(p) for p in sorted(Path(folder).glob("*.json"))}
    parts, placed = [INTRO], set()
    for heading, names in SECTIONS:
        here = [n for n in names if n in tables]
        if here:
            parts.append(f"## {heading}\n")
            parts += [tables[n].markdown() for n in here]
            placed |= set(here)
    rest = [n for n in tables if n not in placed]
    if rest:
        parts.append("## Other\n")
        parts += [tables[n].markdown() for n in rest]
    return "\n".join(parts)


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--check", action="store_true", help="compare, do not write")
    ap.add_argument("--out", type=Path, default=PAGE)
    args = ap.parse_args(argv)
    text = render()
    if args.check:
        same = args.out.exists() and args.out.read_text() == text
        print(f"{args.out}: {'up to date' if same else 'differs from the tables'}")
        sys.exit(0 if same else 1)
    args.out.write_text(text)
    print(f"wrote {args.out} ({len(text.encode()) / 1024:.1f} KB)")


if __name__ == "__main__":
    main()
