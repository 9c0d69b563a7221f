"""Training steps on the CPU in each form the trainer could run them: memory format, precision,
Inductor, torch's threads.

    python -m benchmarks.cpu_train [--resolution 128] [--batch N] [--rounds 5] [--forms ...]

For the default recipe's network and the paper's at ``--resolution``, each at its own batch
(or every one at ``--batch``), one training step (forward, the recipe's loss, backward,
Adam) on a fixed synthetic batch, in each form:
channels_last in fp32 (the trainer's format on every device: ``trainer.training.trainee.Rank.fmt``),
channels_last in bf16 autocast (what the trainer runs on a CPU with AMX or AVX512-BF16:
``trainer.precision``),
contiguous (NCHW), ``torch.compile`` (Inductor's C++ backend) and one torch thread instead
of all (channels_last, fp32). Every form is timed in turn, round after round (``--rounds``),
so a drift of the machine falls on all alike; the table has the median images a second, each
form's ratio to its recipe's channels_last one and to the paper's recipe's in the same form
(at their own batches, what a training run of each goes at). The scene buffers are zeros (a
step's time does not depend on them).
"""

from __future__ import annotations

import argparse
import statistics
import time

import torch

from benchmarks.results import Table, save
from trainer.model import ModelConfig
from trainer.networks import build_model
from trainer.precision import cpu_has_bf16_units
from trainer.training.config import RECIPES, TrainConfig
from trainer.training.losses import RendererLoss, mixed_term
from trainer.training.train import network_config


def step_fn(cfg: ModelConfig, loss: str, batch: int, fmt, compiled: bool, autocast=None):
    """One training step of a fresh network of ``cfg`` on a fixed batch, as a function;
    ``autocast``: the dtype of its forward pass (None: fp32)."""
    torch.manual_seed(0)
    model = build_model(cfg).to(memory_format=fmt)
    opt = torch.optim.Adam(model.parameters(), 1e-4)
    crit = RendererLoss(mixed=mixed_term(loss))
    r = cfg.resolution
    x = torch.rand(batch, cfg.in_channels, r, r).contiguous(memory_format=fmt)
    light, target = torch.rand(batch, 4), torch.rand(batch, 3, r, r)
    net = torch.compile(model) if compiled else model

    def step():
        with torch.autocast("cpu", dtype=autocast, enabled=autocast is not None):
            loss = crit(net(x, light), target)
        loss.backward()
        opt.step()
        opt.zero_grad(set_to_none=True)

    return step


#: name: (memory format, compiled, torch threads or None for all, autocast dtype or None); the
#: first is the unit of the ratios
FORMS = {
    "channels_last": (torch.channels_last, False, None, None),
    "bf16 autocast": (torch.channels_last, False, None, torch.bfloat16),
    "contiguous": (torch.contiguous_format, False, None, None),
    "torch.compile": (torch.channels_last, True, None, None),
    "one thread": (torch.channels_last, False, 1, None),
}
BASE = next(iter(FORMS))


def timed(step, threads: int | None, repeat: int = 2) -> float:
    """Seconds a step, the mean of ``repeat``, with ``threads`` torch threads (None: all)."""
    before = torch.get_num_threads()
    torch.set_num_threads(threads or before)
    try:
        t0 = time.perf_counter()
        for _ in range(repeat):
            step()
        return (time.perf_counter() - t0) / repeat
    finally:
        torch.set_num_threads(before)


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--resolution", type=int, default=128)
    ap.add_argument("--batch", type=int, default=None,
                    help="every recipe's batch (default: each recipe's own)")  # fmt: skip
    ap.add_argument("--rounds", type=int, default=5)
    ap.add_argument("--name", default=None, help="the table's name (default cpu-train-R)")
    ap.add_argument(
        "--forms",
        default=",".join(FORMS),
        help=f"comma-separated forms to time ({BASE} always runs: the ratios' base)",
    )
    args = ap.parse_args(argv)
    if args.rounds < 1 or (args.batch is not None and args.batch < 1):
        ap.error("--rounds and --batch must be at least 1")
    forms = [BASE] + [f for f in args.forms.split(",") if f and f != BASE]
    unknown = [f for f in forms if f not in FORMS]
    if unknown:
        ap.error(f"unknown form {unknown[0]!r} (forms: {', '.join(FORMS)})")
    table = Table(
        title=f"Training steps on the CPU (`python -m benchmarks.cpu_train`): "
        f"{args.resolution}², " + (f"batch {args.batch}" if args.batch else "each recipe's batch"),
        columns=["recipe", "batch", "form", "images/s", f"x {BASE}", "x paper"],
        notes=[f"medians of {args.rounds} rounds, every recipe and form timed in turn; a "
               f"synthetic batch, torch's {torch.get_num_threads()} threads unless one; x paper: "
               "against the paper's recipe in the same form",
               "the trainer trains in channels_last, in bf16 autocast on a CPU with AMX tiles or "
               "AVX512-BF16 "
               f"(`--precision auto`; this one: {'yes' if cpu_has_bf16_units() else 'no'})"],
    )  # fmt: skip
    steps, batches = {}, {}
    for recipe in RECIPES:
        train = TrainConfig(store=("-",), recipe=recipe)
        batches[recipe] = batch = args.batch or train.batch_size
        cfg = network_config(train, args.resolution)
        loss = "l1" if train.loss == "l1+vgg" else train.loss  # no VGG16 weights here
        for name in forms:
            fmt, compiled, threads, autocast = FORMS[name]
            steps[recipe, name] = (step_fn(cfg, loss, batch, fmt, compiled, autocast), threads)
            for _ in range(2):  # warm-up (and the compile)
                timed(*steps[recipe, name], repeat=1)
    times = {key: [] for key in steps}
    for _ in range(args.rounds):
        for key, (step, threads) in steps.items():
            times[key].append(timed(step, threads))
    rate = {(r, n): batches[r] / statistics.median(ts) for (r, n), ts in times.items()}
    for (recipe, name), images in rate.items():
        base, paper = rate[recipe, BASE], rate["paper", name]
        row = [recipe, batches[recipe], name, round(images, 1), round(images / base, 2),
               round(images / paper, 2)]  # fmt: skip
        table.rows.append(row)
        print(f"{recipe:<12}{batches[recipe]:>3}  {name:<16}{row[3]:8.1f} images/s  "
              f"{row[4]:5.2f}x  {row[5]:5.2f}x paper")  # fmt: skip
    save(args.name or f"cpu-train-{args.resolution}", table)


if __name__ == "__main__":
    main()
