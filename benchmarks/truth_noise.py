"""How noisy the learning benchmark's ground truth is, and what its rows score without that noise.

    python -m benchmarks.truth_noise --budget 64000 --rows onecycle,shaderball,sb-w48

The truth is a Cycles render at the store's 32 spp: every row's error against it includes the
render's own noise, which no network should predict. The held-out samples of the learning
store are rendered again at the same samples per pixel with the next Cycles seed (once, kept
beside the runs in ``benchmarks/.cache/learning/R/again.npz``). Two independent renders
differ by twice the noise's variance, so per sample ``var = MSE(truth, again) / 2`` in
display space, and a network's error against the truth is its error against the truth's
mean plus ``var``:

- ``ceiling``: ``-10 log10(var)``, what a perfect prediction of the truth's mean scores against
  the truth; no row's PSNR can mean more;
- each row's PSNR against the truth (as ``benchmarks.learning`` scores it) and without the
  noise, ``-10 log10(MSE - var)`` (floored at a hundredth of ``var``), both means over the
  held-out samples;
- the second renders' LDR-FLIP against the truth: what the noise alone scores in the
  perceptual measure (FLIP does not split into parts as the squared error does), beside the
  rows' FLIP in ``benchmarks.learning``'s table.

The rows are read from ``benchmarks.learning``'s run folders (trained there first).
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
import torch

from benchmarks.learning import CACHE, ROWS, ensure_store
from benchmarks.results import Table, save
from benchmarks.store_renders import render_again
from storage.backend import write_atomic
from storage.reader import Store
from trainer.rendering.evaluate import test_split
from trainer.rendering.load import load_renderer
from trainer.samples import SampleReader
from trainer.scoring import flip
from trainer.training.config import absolute_store


def again(store: Store, samples: list[int], spp: int, path: Path) -> np.ndarray:
    """The samples' second renders, from ``path`` when it holds these samples of this store
    at ``spp`` (a local store by its absolute path, however it was named)."""
    url = absolute_store(store.url)
    if path.exists():
        with np.load(path) as z:
            if (str(z["store"]), list(z["samples"]), int(z["spp"])) == (url, samples, spp):
                return z["renders"]
    renders = render_again(store, samples, spp, seed_offset=1)[0]
    arrays = {"store": url, "samples": np.array(samples), "spp": spp, "renders": renders}
    write_atomic(path, lambda f: np.savez(f, **arrays))  # a killed run leaves no part of it
    return renders


def mse(a: torch.Tensor, b: torch.Tensor) -> np.ndarray:
    return ((a - b) ** 2).flatten(1).mean(1).double().numpy()


def row_mse(run: Path, split, batch: int = 16) -> np.ndarray:
    """Per-sample MSE of a run's network against the truth on ``split``, in display space."""
    renderer, reader = load_renderer(run, "cpu"), SampleReader(split)
    out = []
    for lo in range(0, len(split), batch):
        b = reader.batch(np.arange(lo, min(lo + batch, len(split))))
        with torch.no_grad():
            pred = renderer.render_batch(b["maps"], b["light"]).cpu()
        out.append(mse(pred, renderer.tonemap(b["render"])))
    return np.concatenate(out)


def psnr(m: np.ndarray) -> float:
    return float((-10 * np.log10(m)).mean())


def main(argv: list[str] | None = None) -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--resolution", type=int, default=64)
    p.add_argument("--budget", type=int, default=64_000)
    p.add_argument("--rows", default="onecycle,shaderball")
    p.add_argument("--work", type=Path, default=CACHE / "learning")
    p.add_argument("--results", type=Path, default=None, help="folder of the result table")
    p.add_argument("--name", default=None, help="the table's name (default learning-R-noise)")
    p.add_argument("--store", default=None, help="the store the rows trained on (benchmarks."
                   "learning --store), instead of the cached one")  # fmt: skip
    args = p.parse_args(argv)
    names = args.rows.split(",")
    if unknown := [n for n in names if n not in ROWS]:
        p.error(f"unknown row {unknown[0]!r}: one of {', '.join(ROWS)}")
    store = Store(args.store or ensure_store(args.resolution))
    work = args.work / str(store.layout.resolution)
    runs = [work / str(args.budget) / n for n in names]
    if missing := [r for r in runs if not (r / "result.json").exists()]:
        p.error(f"{missing[0]} is not trained: run benchmarks.learning with its row first")
    first = load_renderer(runs[0], "cpu")
    split = test_split(first, None, None)  # every row of a budget holds out the same samples
    samples = [int(k) for _, k in split.refs.tolist()]
    spp = int(store.settings["samples"])
    second = again(store, samples, spp, work / "again.npz")
    tonemap = first.tonemap
    truth = tonemap(torch.from_numpy(np.stack([store.render(i) for i in samples])))
    shown = tonemap(torch.from_numpy(second))
    var = mse(truth, shown) / 2
    noise_flip = float(flip(shown, truth).mean())
    t = Table(
        f"The learning benchmark's truth and its noise: {store.layout.resolution}², "
        f"{args.budget:,} passes, held-out samples",
        ["row", "PSNR dB against the truth", "PSNR dB without its noise"],
        notes=[
            f"{len(samples)} held-out samples rendered again at {spp} spp with other Cycles "
            "seeds: half the mean squared difference of the two renders is the truth's noise",
            f"ceiling: a perfect prediction of the truth's mean scores {psnr(var):.2f} dB "
            "against the truth",
            f"the second renders against the truth: LDR-FLIP {noise_flip:.4f}, the noise alone",
        ],
    )
    for name, run in zip(names, runs, strict=True):
        m = row_mse(run, split)
        t.rows.append([name, round(psnr(m), 2), round(psnr(np.maximum(m - var, var / 100)), 2)])
    print(t.markdown(), flush=True)
    name = args.name or f"learning-{store.layout.resolution}-noise"
    save(name, t, *([args.results] if args.results else []))


if __name__ == "__main__":
    main()
