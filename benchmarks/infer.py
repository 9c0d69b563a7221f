"""Inference benchmark at 400²: ms per frame at batch 1, frames/s batched.

    .venv/bin/python -m benchmarks.infer [--batch 8] [--iters 20] [--device auto]

Rows: eager fp32 (every device); on CUDA also bf16 + channels_last eager, and a CUDA-graph
replay (``trainer.infer.GraphedRenderer``). The network is the paper's (width 64, skips) with
fresh weights (speed does not depend on them); inputs are real maps and suns from the
benchmark store (``benchmarks.trainstore``). Times are medians over ``--iters`` after warm-up,
each synchronised on CUDA.
"""

from __future__ import annotations

import argparse
import statistics
import time

import torch

from benchmarks.train import device_name
from benchmarks.trainstore import DEFAULT, ensure_store
from trainer.data import Catalog, SampleReader
from trainer.infer import GraphedRenderer, pick_device
from trainer.model import ModelConfig, NeuralRenderer
from trainer.targets import model_inputs


def timed(fn, iters: int, cuda: bool) -> float:
    """Median seconds of ``fn()`` over ``iters`` runs (after 3 warm-up runs)."""
    times = []
    for i in range(iters + 3):
        if cuda:
            torch.cuda.synchronize()
        t0 = time.perf_counter()
        fn()
        if cuda:
            torch.cuda.synchronize()
        if i >= 3:
            times.append(time.perf_counter() - t0)
    return statistics.median(times)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--store", default=DEFAULT)
    ap.add_argument("--batch", type=int, default=8)
    ap.add_argument("--iters", type=int, default=20)
    ap.add_argument("--device", default="auto", choices=["auto", "cuda", "cpu"])
    args = ap.parse_args()
    device = pick_device(args.device)
    cuda = device.type == "cuda"
    split = Catalog.snapshot([ensure_store(args.store)], 0, 0.0, None).split("train")
    data = SampleReader(split).batch(list(range(min(args.batch, len(split)))))
    reps = -(-args.batch // len(data["id"]))
    x_all = model_inputs(data["maps"]).repeat(reps, 1, 1, 1)[: args.batch].to(device)
    l_all = data["light"].repeat(reps, 1)[: args.batch].to(device)
    model = NeuralRenderer(ModelConfig(resolution=400)).to(device).eval()

    rows = []

    def eager(x, light, bf16: bool):
        with torch.inference_mode(), torch.autocast(device.type, torch.bfloat16, enabled=bf16):
            return model(x, light)

    for name, bf16, fmt in [("eager fp32", False, torch.contiguous_format)] + (
        [("eager bf16 channels_last", True, torch.channels_last)] if cuda else []
    ):
        model.to(memory_format=fmt)
        x1, xb = x_all[:1].contiguous(memory_format=fmt), x_all.contiguous(memory_format=fmt)
        one = timed(lambda x1=x1, bf16=bf16: eager(x1, l_all[:1], bf16), args.iters, cuda)
        many = timed(lambda xb=xb, bf16=bf16: eager(xb, l_all, bf16), args.iters, cuda)
        rows.append((name, one * 1e3, args.batch / many))
    if cuda:
        g1, gb = GraphedRenderer(model, 1), GraphedRenderer(model, args.batch)
        one = timed(lambda: g1(x_all[:1], l_all[:1]), args.iters, cuda)
        many = timed(lambda: gb(x_all, l_all), args.iters, cuda)
        rows.append(("CUDA graph bf16", one * 1e3, args.batch / many))
    print(f"\ndevice: {device_name(args.device)}; 400², batch {args.batch} for frames/s")
    print(f"{'mode':<28}{'ms/frame (b=1)':>16}{'frames/s':>12}")
    for name, ms, fps in rows:
        print(f"{name:<28}{ms:>16.2f}{fps:>12.1f}")


if __name__ == "__main__":
    main()
