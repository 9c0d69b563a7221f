"""What one quality run is made of (``make quality``, :mod:`benchmarks.quality`): its scales,
where its stores and runs live, the farm and trainer commands that make them, and its work
folder's records. Shared by the run (``benchmarks.quality``), its report
(``benchmarks.quality_report``) and the side-by-side timing (``benchmarks.frame_times``)."""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

from storage.backend import write_atomic

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
    epochs: int  # the default recipe's run on the training set
    paper_epochs: int  # the paper's U-Net's runs (with and without skips)
    fixed_epochs: int
    batch: int  # the paper's runs' batch
    timing_count: int  # renders timed per Cycles setting
    workers: int = 0  # Blender workers a render job (0: the farm's default, one a CPU)
    loader_workers: int = 1  # DataLoader processes a training run (0: read in the trainer)
    width: int = 64  # the paper's U-Nets' first level (the tiny scale tests the steps)
    recipe_width: int | None = None  # the default recipe's (None: the recipe's own)


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
        epochs=12,  # what one session fits on 2 cores; raise it and rerun to resume
        paper_epochs=12,  # as many image passes as ours (its batch is twice ours)
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
        paper_epochs=1,
        fixed_epochs=1,
        batch=2,
        timing_count=1,
        workers=1,  # a few frames a job: one Blender load, not one a CPU
        loader_workers=0,  # 8 samples a run: a spawned loader's own torch import outweighs them
        width=16,  # a sixteenth of the paper's cost: the tiny scale checks every step, not scores
        recipe_width=8,
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
        """``(run name, training store, extra trainer arguments)``: ``unet`` the default
        recipe, ``paper`` and ``unet-noskips`` the paper's U-Net with and without skips (L1:
        no VGG16 weights here), on the fixed-sun set the default recipe and Zsolnai-Fehér."""
        s = self.scale
        ours = ["--recipe", "shaderball"]
        ours += ["--width", str(s.recipe_width)] if s.recipe_width else []
        paper = ["--recipe", "paper", "--loss", "l1", "--batch-size", str(s.batch)]
        runs = {"ours": s.epochs, "paper": s.paper_epochs, "fixed": s.fixed_epochs}
        epochs = {k: ["--epochs", str(v)] for k, v in runs.items()}
        return [
            ("unet", "train", [*ours, *epochs["ours"]]),
            ("paper", "train", [*paper, "--width", str(s.width), *epochs["paper"]]),
            ("unet-noskips", "train",
             [*paper, "--width", str(s.width), "--no-skips", *epochs["paper"]]),
            ("unet-fixed", "train-fixed", [*ours, *epochs["fixed"]]),
            ("zf-fixed", "train-fixed", [*paper, "--model", "zf", *epochs["fixed"]]),
        ]  # fmt: skip


def load_json(path: Path) -> dict:
    """A work folder's JSON record (``{}`` before its first :func:`save_json`)."""
    return json.loads(path.read_text()) if path.exists() else {}


def save_json(path: Path, data: dict) -> None:
    """Replace a work folder's JSON record whole: a run killed while writing leaves the old."""
    write_atomic(path, lambda f: f.write(json.dumps(data, indent=1).encode()))
