"""What the renderer is worth: the paper's Table 1 reproduced here, in one command.

    make quality                                   # the full scale (hours on 2 cores; resumes)
    .venv/bin/python -m benchmarks.quality --scale tiny --work /tmp/q --doc /tmp/q/quality.md

Every step resumes where it stopped, so a run can span sessions (the stores are farm stores,
the runs are trainer runs):

1. **renders** (``farm submit``): the training set; a held-out test set of other materials
   (the same sources, another ``--seed``: whole materials never trained on); Cycles baselines
   of the test set at 1, 2, 4 and 16 spp, raw and with OpenImageDenoise (same sources and
   seed, so they pair with the test set sample by sample); a fixed-sun set of uniform
   materials for the Zsolnai-Fehér baseline (train and test) and its 2 spp + OIDN baseline.
2. **reference**: a few test samples rendered again at 2,048 spp (how far the ground truth
   itself is from converged: the ceiling of any PSNR measured against it).
3. **training** (``trainer train``, L1; the VGG16 weights are not on these machines): the
   U-Net, the U-Net without skips, and on the fixed-sun set the U-Net and Zsolnai-Fehér.
4. **evaluation**: PSNR, SSIM, FLIP per material kind, all against the test set's renders
   (``trainer.rendering.evaluate.Tally``); ms per frame of every method on this machine.
5. **report**: ``--doc`` (markdown tables) and ``--img`` (a labelled picture grid).
6. **picture**: ``--picture``, the viewer on the main network with a held-out material beside
   its Cycles render, in headless Chromium (``benchmarks.viewer_picture``: the procedural
   sample of median PSNR, not the best); its sample and scores beside it as JSON.
"""

from __future__ import annotations

import argparse
import json
import os
import shlex
import subprocess
import sys
from dataclasses import asdict
from pathlib import Path

from benchmarks import quality_report as report
from benchmarks import viewer_picture
from benchmarks.quality_plan import SCALES, Plan
from trainer import checkpoint

BIN = Path(sys.executable).parent
STEPS = ("renders", "reference", "train", "report", "picture")


def sh(cmd: list[str], log: Path | None = None) -> None:
    """Run ``cmd`` (printed first); its output goes to ``log`` when given; raise on failure."""
    print("$ " + shlex.join(cmd), flush=True)
    env = {**os.environ, "RAY_AUTH_MODE": os.environ.get("RAY_AUTH_MODE", "disabled")}
    if log is None:
        subprocess.run(cmd, check=True, env=env)
        return
    with open(log, "a") as f:
        r = subprocess.run(cmd, stdout=f, stderr=subprocess.STDOUT, env=env)
    if r.returncode:
        tail = log.read_text().strip().splitlines()[-1:] or ["(no output)"]
        raise SystemExit(f"failed ({r.returncode}): {shlex.join(cmd)}: {tail[0]} (log: {log})")


def render_all(plan: Plan) -> None:
    """Every store; ``farm submit`` resumes a store that is there and skips a finished one."""
    logs = plan.work / "logs"
    logs.mkdir(parents=True, exist_ok=True)
    for name, args in plan.renders():
        sh([str(BIN / "farm"), "submit", *args], logs / f"farm-{name}.log")


def train_all(plan: Plan) -> None:
    """Every run to its last epoch (resumed from its latest checkpoint)."""
    s = plan.scale
    for name, store, extra in plan.trainings():
        run = plan.run(name)
        last = checkpoint.latest(run)
        epochs = int(extra[extra.index("--epochs") + 1])
        if last is not None and checkpoint.load(last)["epoch"] >= epochs:
            continue
        cmd = [str(BIN / "trainer"), "train", "--store", plan.store(store), "--out", str(run),
               "--holdout-fraction", "0", "--val-samples", "0",
               "--workers", str(s.loader_workers), "--checkpoint-every", "200",
               "--log-every", "20", *extra,
               *(["--resume"] if last is not None else [])]  # fmt: skip
        run.parent.mkdir(parents=True, exist_ok=True)
        sh(cmd, plan.work / "logs" / f"train-{name}.log")


def picture(plan: Plan, out: Path) -> None:
    """The viewer on the main network and a held-out material (needs the report's scores)."""
    scores = plan.work / "scores" / "unet--test.csv"
    if not scores.exists():
        raise SystemExit(f"{scores}: no scores of the main network yet: run the report step")
    info = viewer_picture.make_picture(plan.run("unet"), plan.store("test"), scores, out)
    print(viewer_picture.describe(info), flush=True)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scale", default="full", choices=sorted(SCALES))
    ap.add_argument("--work", type=Path, default=None, help="default: out/quality (tiny: -tiny)")
    ap.add_argument("--doc", type=Path, default=Path("docs/quality.md"))
    ap.add_argument("--img", type=Path, default=None, help="default: beside --doc, img/")
    ap.add_argument(
        "--picture",
        type=Path,
        default=None,
        help="the viewer's picture (default: beside --doc, img/viewer.png)",
    )
    ap.add_argument("--steps", default=",".join(STEPS),
                    help="comma-separated steps to run")  # fmt: skip
    args = ap.parse_args()
    scale = SCALES[args.scale]
    work = args.work or Path("out/quality" if args.scale == "full" else "out/quality-tiny")
    plan = Plan(scale, work.absolute())
    plan.work.mkdir(parents=True, exist_ok=True)
    steps = set(args.steps.split(","))
    unknown = steps - set(STEPS)
    if unknown:
        ap.error(f"unknown step(s): {', '.join(sorted(unknown))}")
    print(f"quality: scale {args.scale} {json.dumps(asdict(scale))}; work {plan.work}", flush=True)
    if "renders" in steps:
        render_all(plan)
    if "reference" in steps:
        report.reference(plan)
    if "train" in steps:
        train_all(plan)
    if "report" in steps:
        img = args.img or args.doc.parent / "img" / "quality-grid.png"
        report.write(plan, args.scale, args.doc, img)
    if "picture" in steps:
        picture(plan, args.picture or args.doc.parent / "img" / "viewer.png")


if __name__ == "__main__":
    main()
