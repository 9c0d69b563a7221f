"""The FLOPs of one training image pass, by row of ``benchmarks.learning``
(:mod:`benchmarks.flops` counts them), with what the paper's 1.47 M passes add up to. Divide
a row's passes per second on a GPU by a pass's FLOPs to see how much of the chip a run used,
or the FLOPs of a run by the seconds it has to see the rate it needs.

    python -m benchmarks.pass_flops                  # the rows gpu.sh learn trains, at 64²
    python -m benchmarks.pass_flops --rows default,paper,default-w32 --resolution 128
"""

from __future__ import annotations

import argparse

from benchmarks.flops import count
from benchmarks.learning import ROWS
from benchmarks.results import Table, save

PAPER_PASSES = 1_470_000


def table(counts: list[dict]) -> Table:
    """The table of ``counts``: each :func:`benchmarks.flops.count` with its row and
    resolution."""
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
    counts = []
    for n in args.resolution or [64]:
        for row in rows:
            try:
                counts.append({"row": row, "resolution": n, **count(ROWS[row][1], n)})
            except ValueError as exc:
                p.error(f"row {row}: {exc}")
    t = table(counts)
    print(t.markdown())
    print(f"saved {save(args.name, t)}")


if __name__ == "__main__":
    main()
