"""How many of float16's 10 mantissa bits a store's renders need (``farm submit
--render-bits``): for each count kept, the bytes a render takes as the store keeps it (one
render a chunk, zstd at the writer's level) and the rounding's error against the render,
both tonemapped as the trainer's targets are; beside them, the same error of a second render
of those samples by Blender with other Cycles seeds, the Monte Carlo noise the rounding adds to.

    python -m benchmarks.render_bits --store out/gpu-learn-64.zarr

The store must keep every bit (no ``render_bits`` setting): it is the reference.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
from numcodecs import Zstd

from benchmarks.results import FOLDER, Table, save
from benchmarks.store_renders import render_again
from render_jobs.tonemap import tonemap
from storage.reader import Store
from storage.schema import FLOAT16_MANTISSA_BITS, RENDER_BITS, round_renders
from storage.writer import ZSTD_LEVEL

BITS = (10, 8, 7, 6, 5, 4)
#: moves every Cycles seed of the second render away from the store's
SEED_OFFSET = 7919


def psnr(a: np.ndarray, b: np.ndarray) -> float:
    """Mean over samples of the PSNR of tonemapped ``(N, 3, H, W)`` ``a`` against ``b``."""
    ta, tb = (np.stack([tonemap(x) for x in y]) for y in (a, b))
    mse = ((ta - tb) ** 2).reshape(len(ta), -1).mean(1)
    return float(np.mean(10 * np.log10(1 / np.maximum(mse, 1e-20))))


def chunk_bytes(renders: np.ndarray) -> float:
    """Mean bytes of one render compressed as the store's chunk is."""
    c = Zstd(level=ZSTD_LEVEL)
    return float(np.mean([len(c.encode(r.tobytes())) for r in renders]))


def bits_rows(renders: np.ndarray) -> list[list]:
    """One row a count of bits: bytes a render, their share of all 10 bits', the largest
    relative error of a normal value (a subnormal one, under 6.1e-5, has fewer bits to keep),
    the PSNR of the rounded renders against the renders."""
    full = chunk_bytes(renders)
    normal = np.isfinite(renders) & (np.abs(renders) >= np.finfo(np.float16).smallest_normal)
    rows = []
    for bits in BITS:
        kept = round_renders(renders, bits)
        size = chunk_bytes(kept)
        rel = np.abs(kept[normal].astype(np.float32) / renders[normal].astype(np.float32) - 1)
        same = bits == FLOAT16_MANTISSA_BITS
        rows.append([
            f"{bits} bits", round(size), round(size / full, 3), f"{rel.max():.2e}",
            None if same else round(psnr(kept, renders), 2),
        ])  # fmt: skip
    return rows


def main(argv: list[str] | None = None) -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--store", default="out/gpu-learn-64.zarr")
    p.add_argument("--samples", type=int, default=500, help="the store's first samples")
    p.add_argument("--noise-samples", type=int, default=200,
                   help="of those, how many Blender renders again")  # fmt: skip
    p.add_argument("--name", default="render-bits")
    p.add_argument("--results", type=Path, default=FOLDER, help="where the table goes")
    args = p.parse_args(argv)
    store = Store(args.store)
    if store.settings.get(RENDER_BITS) is not None:
        p.error(f"{args.store} keeps {store.settings[RENDER_BITS]} bits, not every one")
    n = min(args.samples, store.layout.num_samples)
    renders = np.stack([np.asarray(store.render(i)) for i in range(n)])
    rows = bits_rows(renders)
    k = min(args.noise_samples, n)
    again, _ = render_again(store, list(range(k)), store.settings["samples"], SEED_OFFSET)
    spp = store.settings["samples"]
    rows.append([f"another {spp}-spp render", None, None, None, round(psnr(again, renders[:k]), 2)])
    r = store.layout.resolution
    t = Table(
        title=f"Render mantissa bits: bytes and error, {r}², {spp} spp",
        columns=[
            "kept",
            "bytes a render",
            "x all 10",
            "largest relative error (normal values)",
            "PSNR dB against the render",
        ],  # fmt: skip
        rows=rows,
        notes=[
            f"the first {n} renders of {args.store} (float16, every bit); bytes: each render "
            f"zstd-compressed (level {ZSTD_LEVEL}) alone, as a store chunk is",
            "PSNR: tonemapped (Reinhard, sRGB, +1 stop: the trainer's targets), mean over "
            f"samples; the last row: the first {k} samples rendered again by Blender with "
            "other Cycles seeds, the render's own noise (twice its variance)",
        ],
    )
    print(t.markdown())
    print("wrote", save(args.name, t, args.results))


if __name__ == "__main__":
    main()
