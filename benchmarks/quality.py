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
   (``trainer.evaluate.Tally``); ms per frame of every method on this machine.
5. **report**: ``--doc`` (markdown tables) and ``--img`` (a labelled picture grid).
"""

from __future__ import annotations

import argparse
import json
import os
import shlex
import subprocess
import sys
import time
from dataclasses import asdict, dataclass
from pathlib import Path

BIN = Path(sys.executable).parent
FIXED_SUN = (-0.4, -0.6, 0.7, 3.0)  # from the front left, 44° up, turbidity 3


@dataclass(frozen=True)
class Scale:
    """Sizes of one quality run."""

    resolution: int
    samples: int  # the ground truth's spp
    train: tuple[int, int]  # uniform, procedural materials
    test: tuple[int, int]
    suns: int
    fixed: tuple[int, int]  # uniform materials under the fixed sun: train, test
    baselines: tuple[int, ...]  # Cycles spp, each raw and with OIDN
    reference_spp: int
    reference_count: int
    epochs: int
    fixed_epochs: int
    batch: int
    timing_count: int  # renders timed per Cycles setting
    workers: int = 0  # Blender workers a render job (0: the farm's default, one a CPU)
    loader_workers: int = 1  # DataLoader processes a training run (0: read in the trainer)
    width: int = 64  # the U-Nets' first level (the paper's 64; the tiny scale tests the steps)


SCALES = {
    "full": Scale(
        resolution=128,
        samples=64,
        train=(250, 250),
        test=(25, 25),
        suns=5,
        fixed=(500, 50),
        baselines=(1, 2, 4, 16),
        reference_spp=2048,
        reference_count=6,
        epochs=3,  # what one 3-hour session fits on 2 cores; raise it and rerun to resume
        fixed_epochs=10,
        batch=8,
        timing_count=3,
    ),
    "tiny": Scale(
        resolution=32,
        samples=4,
        train=(2, 2),
        test=(3, 2),  # 5 materials: the fewest that get intervals (trainer.intervals)
        suns=2,
        fixed=(6, 2),
        baselines=(1,),  # raw and OIDN: every step and comparison of the report
        reference_spp=16,
        reference_count=2,
        epochs=1,
        fixed_epochs=1,
        batch=2,
        timing_count=1,
        workers=1,  # a few frames a job: one Blender load, not one a CPU
        loader_workers=0,  # 8 samples a run: a spawned loader's own torch import outweighs them
        width=16,  # a sixteenth of the paper's cost: the tiny scale checks every step, not scores
    ),
}


def baseline_store(spp: int, oidn: bool) -> str:
    """The name of the test set's Cycles baseline store at ``spp``, denoised or raw."""
    return f"test-{spp}spp{'-oidn' if oidn else ''}"


@dataclass(frozen=True)
class Plan:
    """Where everything of one run lives, and the commands that make it."""

    scale: Scale
    work: Path

    def store(self, name: str) -> str:
        return str(self.work / f"{name}.zarr")

    def run(self, name: str) -> Path:
        return self.work / "runs" / name

    def renders(self) -> list[tuple[str, list[str]]]:
        """``(store name, farm submit arguments)`` in the order they are rendered."""
        s = self.scale
        common = ["--resolution", str(s.resolution), "--no-ray-dashboard",
                  *(["--workers", str(s.workers)] if s.workers else [])]  # fmt: skip
        sets = lambda u, p: [*(["-m", f"uniform:{u}"] if u else []),  # noqa: E731
                             *(["-m", f"procedural:{p}"] if p else [])]  # fmt: skip
        test = [*sets(*s.test), "--seed", "1", "--suns", str(s.suns)]
        fixed = ["--suns", "1", "--fixed-sun", ",".join(map(str, FIXED_SUN[:3])),
                 "--fixed-turbidity", str(FIXED_SUN[3])]  # fmt: skip
        out = [("test", [*test, "--samples", str(s.samples)])]
        for spp in s.baselines:
            out.append((baseline_store(spp, False), [*test, "--samples", str(spp)]))
            out.append((baseline_store(spp, True), [*test, "--samples", str(spp), "--denoise"]))
        fixed_test = ["-m", f"uniform:{s.fixed[1]}", "--seed", "1", *fixed]
        out.append(("test-fixed", [*fixed_test, "--samples", str(s.samples)]))
        out.append(("test-fixed-2spp-oidn", [*fixed_test, "--samples", "2", "--denoise"]))
        out.append(("train-fixed", ["-m", f"uniform:{s.fixed[0]}", "--seed", "0", *fixed,
                                    "--samples", str(s.samples)]))  # fmt: skip
        out.append(("train", [*sets(*s.train), "--seed", "0", "--suns", str(s.suns),
                              "--samples", str(s.samples)]))  # fmt: skip
        return [(name, [*args, *common, "-o", self.store(name)]) for name, args in out]

    def trainings(self) -> list[tuple[str, str, list[str]]]:
        """``(run name, training store, extra trainer arguments)``."""
        s = self.scale
        ep, fep = ["--epochs", str(s.epochs)], ["--epochs", str(s.fixed_epochs)]
        width = ["--width", str(s.width)]
        return [
            ("unet", "train", [*ep, *width]),
            ("unet-noskips", "train", [*ep, *width, "--no-skips"]),
            ("unet-fixed", "train-fixed", [*fep, *width]),
            ("zf-fixed", "train-fixed", [*fep, "--model", "zf"]),
        ]


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
    """Every run to its last epoch (resumed from its latest checkpoint); wall time kept."""
    from trainer import checkpoint

    s = plan.scale
    times = load_json(plan.work / "train-seconds.json")
    for name, store, extra in plan.trainings():
        run = plan.run(name)
        last = checkpoint.latest(run)
        epochs = int(extra[extra.index("--epochs") + 1])
        if last is not None and checkpoint.load(last)["epoch"] >= epochs:
            continue
        cmd = [str(BIN / "trainer"), "train", "--store", plan.store(store), "--out", str(run),
               "--loss", "l1", "--holdout-fraction", "0", "--batch-size", str(s.batch),
               "--workers", str(s.loader_workers), "--checkpoint-every", "200",
               "--log-every", "20", *extra,
               *(["--resume"] if last is not None else [])]  # fmt: skip
        run.parent.mkdir(parents=True, exist_ok=True)
        t0 = time.perf_counter()
        sh(cmd, plan.work / "logs" / f"train-{name}.log")
        times[name] = times.get(name, 0.0) + time.perf_counter() - t0
        save_json(plan.work / "train-seconds.json", times)


def load_json(path: Path) -> dict:
    """A work folder's JSON record (``{}`` before its first :func:`save_json`)."""
    return json.loads(path.read_text()) if path.exists() else {}


def save_json(path: Path, data: dict) -> None:
    """Replace a work folder's JSON record whole: a run killed while writing leaves the old."""
    from storage.backend import write_atomic

    write_atomic(path, lambda f: f.write(json.dumps(data, indent=1).encode()))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scale", default="full", choices=sorted(SCALES))
    ap.add_argument("--work", type=Path, default=None, help="default: out/quality (tiny: -tiny)")
    ap.add_argument("--doc", type=Path, default=Path("docs/quality.md"))
    ap.add_argument("--img", type=Path, default=None, help="default: beside --doc, img/")
    ap.add_argument("--steps", default="renders,reference,train,report",
                    help="comma-separated steps to run")  # fmt: skip
    args = ap.parse_args()
    scale = SCALES[args.scale]
    work = args.work or Path("out/quality" if args.scale == "full" else "out/quality-tiny")
    plan = Plan(scale, work.absolute())
    plan.work.mkdir(parents=True, exist_ok=True)
    steps = set(args.steps.split(","))
    unknown = steps - {"renders", "reference", "train", "report"}
    if unknown:
        ap.error(f"unknown step(s): {', '.join(sorted(unknown))}")
    print(f"quality: scale {args.scale} {json.dumps(asdict(scale))}; work {plan.work}", flush=True)
    from benchmarks import quality_report as report

    if "renders" in steps:
        render_all(plan)
    if "reference" in steps:
        report.reference(plan)
    if "train" in steps:
        train_all(plan)
    if "report" in steps:
        img = args.img or args.doc.parent / "img" / "quality-grid.png"
        report.write(plan, args.scale, args.doc, img)


if __name__ == "__main__":
    main()
