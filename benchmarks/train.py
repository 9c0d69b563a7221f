"""Training benchmark at 400²: images/s and data-wait share of the real training loop.

    .venv/bin/python -m benchmarks.train [--store out/bench-400.zarr] [--batch 4] [--steps 12]
                                          [--workers 2] [--device auto] [--loss l1]
                                          [--replicate N] [--log-every 4]

Rows: the loader alone (DataLoader over the shards, no model: the data path's ceiling); the
loader feeding a consumer that sleeps ``--step-ms`` a batch (a stand-in for a GPU step) over
``--sim-epochs`` epochs, read in one iteration (as training does) and, for comparison, in one
iteration an epoch (the cost of restarting the workers' read-ahead at every epoch); and
``trainer.training.train.train`` itself (L1, from scratch, ``--max-steps``), whose images/s and data
wait are read from the run's ``log.jsonl`` after the first ``--warmup`` steps. On CUDA the
loop runs with bf16 autocast and channels_last, as in real runs. ``--loss l1+vgg`` times the
perceptual loss with random VGG16 weights (speed does not depend on them). ``--replicate N``
first writes the store N times over into a temporary store (``benchmarks.trainstore``), so
that epochs last long enough at GPU speed.
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

from benchmarks.results import Table, save
from benchmarks.trainstore import DEFAULT, ensure_store, replicate
from trainer import runfiles
from trainer.training.config import TrainConfig
from trainer.training.data import PREFETCH, WORKER_START, Catalog, ShardStream, Split, loader
from trainer.training.losses import vgg16_relu3_3
from trainer.training.train import train


def loader_rate(split: Split, batch: int, workers: int, batches: int) -> float:
    """Images/s of the DataLoader alone over the store's training split (as many epochs as
    it takes, in one iteration, as training reads it, through the trainer's loader)."""
    stream = ShardStream(split, batch=batch, seed=0, buffer=256, epochs=10**6)
    batches_in = iter(loader(stream, workers))
    next(batches_in)  # from the first batch on: worker start-up is not throughput
    t0 = time.perf_counter()
    n = sum(len(next(batches_in)["id"]) for _ in range(batches))
    return n / (time.perf_counter() - t0)


def epoch_end_wait(
    split: Split, batch: int, workers: int, step_ms: float, epochs: int, across: bool
) -> tuple[float, float, float]:
    """Images/s, data-wait share and longest wait (s) of a consumer that spends ``step_ms`` on
    every batch (a stand-in for a GPU step) over ``epochs`` epochs, timed from the first batch
    to the end of the last step (the workers' shutdown is not timed). ``across``: one
    iteration over all epochs, as ``trainer.training.train`` reads; otherwise one iteration an epoch
    (persistent workers), where each epoch's start waits for every worker's first batch."""
    stream = ShardStream(split, batch=batch, seed=0, buffer=256, epochs=epochs if across else None)
    if across:
        batches_in = loader(stream, workers)  # as trainer.training.train makes it
    else:
        batches_in = DataLoader(
            stream, batch_size=None, num_workers=workers, prefetch_factor=PREFETCH,
            persistent_workers=True, multiprocessing_context=WORKER_START,
        )  # fmt: skip
    waits, images, t0 = [], 0, None
    for epoch in range(1 if across else epochs):
        stream.set_position(epoch, 0)
        t = time.perf_counter()
        for b in batches_in:
            if t0 is None:
                t0 = time.perf_counter()
            else:
                waits.append(time.perf_counter() - t)
                images += len(b["id"])
            time.sleep(step_ms / 1000)
            t = time.perf_counter()
    seconds = t - t0
    return images / seconds, sum(waits) / seconds, max(waits)


def device_name(device: str | torch.device) -> str:
    """The GPU's or the CPU's name, for ``--device``'s value or a torch device."""
    device = device.type if isinstance(device, torch.device) else device
    if device == "cuda" or (device == "auto" and torch.cuda.is_available()):
        return torch.cuda.get_device_name()
    return f"CPU ({platform.processor() or platform.machine()}, {torch.get_num_threads()} threads)"


def parser() -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--store", default=DEFAULT)
    ap.add_argument("--batch", type=int, default=4)
    ap.add_argument("--steps", type=int, default=12)
    ap.add_argument("--warmup", type=int, default=4)
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--device", default="auto", choices=["auto", "cuda", "cpu"])
    ap.add_argument("--loss", default="l1", choices=["l1", "l1+vgg"])
    ap.add_argument("--replicate", type=int, default=0, help="copies of the store to train on")
    ap.add_argument("--log-every", type=int, default=1, help="steps per timed window")
    ap.add_argument(
        "--step-ms",
        type=float,
        help="the simulated step of the epoch-end rows (default: twice the loader's time a batch)",
    )
    ap.add_argument(
        "--sim-epochs", type=int, default=6, help="epochs of the epoch-end rows (0: no such rows)"
    )
    return ap


def trainer_log(args: argparse.Namespace, store: str, tmp: str) -> list[dict]:
    """The log of ``args.steps`` steps of the real trainer on ``store`` (a run in ``tmp``;
    the VGG16 of ``--loss l1+vgg`` with random weights: speed does not depend on them)."""
    vgg = None
    if args.loss == "l1+vgg":
        vgg = f"{tmp}/vgg16-random.pth"
        torch.save({f"features.{k}": v for k, v in vgg16_relu3_3().state_dict().items()}, vgg)
    run = f"{tmp}/run"
    cfg = TrainConfig(
        store=(store,), out=run, loss=args.loss, vgg_weights=vgg, batch_size=args.batch,
        workers=args.workers, max_steps=args.steps, log_every=args.log_every,
        holdout_fraction=0.0, device=args.device, checkpoint_every=10**9,
    )  # fmt: skip
    train(cfg)
    return [json.loads(x) for x in (Path(run) / runfiles.LOG).read_text().splitlines()]


def print_table(args, load: float, step_ms: float, ends: dict, log: list[dict]) -> Table:
    """Print the loader's rate, the epoch-end rows and the trainer's rate and data wait after
    ``--warmup`` steps; the same as a :class:`Table`."""
    timed = [r for r in log if r["step"] - r["steps"] >= args.warmup]
    seconds = runfiles.loop_seconds(timed)
    wait = sum(r["data_wait"] * r["images"] / r["images_per_second"] for r in timed) / seconds
    print(f"{'row':<50}{'images/s':>10}{'data wait':>11}{'longest wait':>14}")
    print(f"{'loader only':<50}{load:>10.1f}{'-':>11}{'-':>14}")
    rows = [["loader only", round(load, 1), None, None]]
    for across, label in ((False, "an iteration an epoch"), (True, "one iteration (trainer)")):
        if across not in ends:
            continue
        row = f"loader + {step_ms:.0f} ms steps, {label}"
        rate, share, longest = ends[across]
        print(f"{row:<50}{rate:>10.1f}{share:>11.1%}{longest * 1000:>11.0f} ms")
        rows.append([row, round(rate, 1), f"{share:.1%}", f"{longest * 1000:.0f} ms"])
    row = f"train (steps {args.warmup + 1}-{args.steps})"
    rate = sum(r["images"] for r in timed) / seconds
    print(f"{row:<50}{rate:>10.2f}{wait:>11.1%}{'-':>14}")
    rows.append([row, round(rate, 2), f"{wait:.1%}", None])
    return Table(title="", columns=["row", "images/s", "data wait", "longest wait"], rows=rows)


def main() -> None:
    ap = parser()
    args = ap.parse_args()
    if args.steps <= args.warmup:
        ap.error(f"--steps {args.steps} leaves no step after the --warmup {args.warmup} to time")
    store = ensure_store(args.store)
    with tempfile.TemporaryDirectory(prefix="bench-train-") as tmp:
        if args.replicate > 1:
            store = replicate(store, f"{tmp}/replicated.zarr", args.replicate)
        catalog = Catalog.snapshot([store], 0, 0.0, None)
        split = catalog.split("train")
        load = loader_rate(split, args.batch, args.workers, args.steps)
        step_ms = args.step_ms or 2000 * args.batch / load
        ends = {
            across: epoch_end_wait(
                split, args.batch, args.workers, step_ms, args.sim_epochs, across
            )
            for across in ((False, True) if args.sim_epochs > 0 else ())
        }
        log = trainer_log(args, store, tmp)
    about = (
        f"{catalog.resolution}², batch {args.batch}, {args.workers} workers, loss {args.loss}, "
        f"{len(split)} samples an epoch"
    )
    print(f"\ndevice: {device_name(args.device)}; {about}")
    table = print_table(args, load, step_ms, ends, log)
    table.title = f"Training throughput (`make bench-train`): {about}"
    table.machine = device_name(args.device)
    save("train-cuda" if "CPU" not in table.machine else "train-cpu", table)


if __name__ == "__main__":
    main()
