"""The arithmetic of one training image pass, by row of ``benchmarks.learning``: the
floating-point operations of the network's forward pass, and of a whole pass (forward, loss,
backward), as PyTorch's FLOP counter counts them, with what the paper's 1.47 M passes add up
to. Divide a row's passes per second on a GPU by a pass's FLOPs to see how much of the chip
a run used, or the FLOPs of a run by the seconds it has to see the rate it needs.

    python -m benchmarks.pass_flops                  # the rows gpu.sh learn trains, at 64²
    python -m benchmarks.pass_flops --rows default,paper,default-w32 --resolution 128

The count is exact for a given shape (it depends on no value and no machine); it counts
matrix and convolution FLOPs (a multiply-add is two), not the elementwise work of the
normalizations, activations or optimizer. A network with scene cues is counted as ``trainer
train --preload`` trains it: the cues made once per sample, before the step.
"""

from __future__ import annotations

import argparse

PAPER_PASSES = 1_470_000
#: images in the counted batch (the count scales with it; a few keeps the CPU's work small)
BATCH = 4


def row_network(name: str, resolution: int):
    """Row ``name``'s network (without geometry buffers: the count does not depend on their
    values) and its loss, as ``trainer train`` builds them."""
    from benchmarks.learning import ROWS
    from trainer.networks import build_model
    from trainer.training.config import TrainConfig
    from trainer.training.losses import RendererLoss, mixed_term
    from trainer.training.train import network_config

    cfg = TrainConfig(store=("-",), **ROWS[name][1])
    if "vgg" in cfg.loss:  # the learning rows train without VGG16 weights
        raise ValueError(f"row {name}: its loss {cfg.loss} needs VGG16 weights")
    model = build_model(network_config(cfg, resolution))
    return model, RendererLoss(mixed=mixed_term(cfg.loss))


def count(name: str, resolution: int) -> dict:
    """Row ``name``'s parameters and FLOPs per image at ``resolution``."""
    import torch
    from torch.utils.flop_counter import FlopCounterMode

    torch.manual_seed(0)
    model, loss = row_network(name, resolution)
    n = resolution
    maps = torch.rand(BATCH, model.config.in_channels, n, n)
    light = torch.rand(BATCH, 4)
    target = torch.rand(BATCH, 3, n, n)
    cues = None if model.scene is None else model.scene(maps, light).detach()
    with FlopCounterMode(display=False) as counter:
        out = model(maps, light, cues)
        forward = counter.get_total_flops()
        loss(out, target).backward()
        whole = counter.get_total_flops()
    return {
        "row": name,
        "resolution": resolution,
        "parameters": sum(p.numel() for p in model.parameters()),
        "forward": forward / BATCH,
        "pass": whole / BATCH,
    }


def table(counts: list[dict]):
    from benchmarks.results import Table

    t = Table(
        title="FLOPs of a training image pass",
        columns=["row", "resolution", "parameters (M)", "GFLOP forward", "GFLOP a pass",
                 "PFLOP for 1.47 M passes"],
        notes=["torch.utils.flop_counter over one batch, per image: matrix and convolution "
               "FLOPs (a multiply-add is two) of the forward pass, and of forward, loss and "
               "backward; scene cues made before the step, as trainer train --preload does"],
    )  # fmt: skip
    for c in counts:
        t.rows.append([
            c["row"], f"{c['resolution']}²", round(c["parameters"] / 1e6, 2),
            round(c["forward"] / 1e9, 3), round(c["pass"] / 1e9, 3),
            round(c["pass"] * PAPER_PASSES / 1e15, 2),
        ])  # fmt: skip
    return t


def main(argv: list[str] | None = None) -> None:
    from benchmarks.learning import ROWS
    from benchmarks.results import save

    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--rows", default="paper,default",
                   help="benchmarks.learning rows, comma-separated")  # fmt: skip
    p.add_argument("--resolution", type=int, action="append",
                   help="pixels a side (repeatable; default 64)")  # fmt: skip
    p.add_argument("--name", default="pass-flops", help="the table's name")
    args = p.parse_args(argv)
    rows = [r.strip() for r in args.rows.split(",") if r.strip()]
    unknown = [r for r in rows if r not in ROWS]
    if unknown or not rows:
        p.error(f"--rows: {', '.join(unknown) or 'none given'}: not a benchmarks.learning row")
    try:
        counts = [count(r, n) for n in args.resolution or [64] for r in rows]
    except ValueError as exc:
        p.error(str(exc))
    t = table(counts)
    print(t.markdown())
    print(f"saved {save(args.name, t)}")


if __name__ == "__main__":
    main()
