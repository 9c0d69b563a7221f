"""Training benchmark at 400²: images/s and data-wait share of the real training loop.

    .venv/bin/python -m benchmarks.train [--store out/bench-400.zarr] [--batch 4] [--steps 12]
                                          [--workers 2] [--device auto]

Rows: the loader alone (DataLoader over the shards, no model: the data path's ceiling), and
``trainer.train.train`` itself (L1, from scratch, ``--max-steps``), whose images/s and data
wait are read from the run's ``log.jsonl`` after the first ``--warmup`` steps. On CUDA the
loop runs with bf16 autocast and channels_last, as in real runs.
"""

from __future__ import annotations

import argparse
import json
import platform
import tempfile
import time
from pathlib import Path

import torch
from torch.utils.data import DataLoader

from benchmarks.trainstore import DEFAULT, ensure_store
from trainer.config import TrainConfig
from trainer.data import Catalog, ShardStream
from trainer.train import train


def loader_rate(store: str, batch: int, workers: int, batches: int) -> float:
    """Images/s of the DataLoader alone over the store's training split."""
    split = Catalog.snapshot([store], 0, 0.0, None).split("train")
    stream = ShardStream(split, batch=batch, seed=0, buffer=256)
    loader = DataLoader(stream, batch_size=None, num_workers=workers, persistent_workers=True)
    n, t0, epoch = 0, None, 0
    while n < batches * batch:
        stream.set_position(epoch, 0)
        for b in loader:
            if t0 is None:  # from the first batch on: worker start-up is not throughput
                t0, n = time.perf_counter(), 0
                continue
            n += len(b["id"])
        epoch += 1
    return n / (time.perf_counter() - t0)


def device_name(device: str) -> str:
    if device == "cuda" or (device == "auto" and torch.cuda.is_available()):
        return torch.cuda.get_device_name()
    return f"CPU ({platform.processor() or platform.machine()}, {torch.get_num_threads()} threads)"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--store", default=DEFAULT)
    ap.add_argument("--batch", type=int, default=4)
    ap.add_argument("--steps", type=int, default=12)
    ap.add_argument("--warmup", type=int, default=4)
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--device", default="auto", choices=["auto", "cuda", "cpu"])
    args = ap.parse_args()
    store = ensure_store(args.store)
    load = loader_rate(store, args.batch, args.workers, args.steps)
    with tempfile.TemporaryDirectory(prefix="bench-train-") as run:
        cfg = TrainConfig(
            store=(store,), out=run, loss="l1", batch_size=args.batch, workers=args.workers,
            max_steps=args.steps, log_every=1, holdout_fraction=0.0, device=args.device,
            checkpoint_every=10**9,
        )  # fmt: skip
        train(cfg)
        log = [json.loads(x) for x in (Path(run) / "log.jsonl").read_text().splitlines()]
    timed = [r for r in log if r["step"] > args.warmup]
    seconds = sum(args.batch / r["images_per_second"] for r in timed)
    wait = sum(r["data_wait"] * args.batch / r["images_per_second"] for r in timed) / seconds
    print(f"\ndevice: {device_name(args.device)}; 400², batch {args.batch}, {args.workers} workers")
    print(f"{'row':<28}{'images/s':>10}{'data wait':>11}")
    print(f"{'loader only':<28}{load:>10.1f}{'-':>11}")
    row = f"train (steps {args.warmup + 1}-{args.steps})"
    print(f"{row:<28}{len(timed) * args.batch / seconds:>10.2f}{wait:>11.1%}")


if __name__ == "__main__":
    main()
