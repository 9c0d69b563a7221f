"""How much the network learns per image pass: recipes trained for the same number of image
passes on one store, scored on the same held-out materials.

    make bench-learning     # 64² at 16k and 64k passes, the truth's noise, 128² at 8k (hours)
    python -m benchmarks.learning --resolution 128 --budget 8000 --rows onecycle,default
    python -m benchmarks.learning --budget 800 --rows paper,default --work /tmp/l  # a look

The store (``benchmarks/.cache/learning-R.zarr``) is rendered once by the farm: 100 uniform
and 100 procedural materials x 5 suns at 32 spp; the trainer's seeded split holds 15 % of the
materials out. Each row of :data:`ROWS` runs ``trainer train`` with its settings for the
fewest steps that make at least ``budget`` image passes (:func:`steps_for`: an epoch ends in a
short batch where the batch does not divide the training split), on one CPU process with
one loader worker, then its network is scored on
every held-out sample (PSNR with its 95 % interval over materials, SSIM, FLIP;
``trainer.rendering.evaluate``). Throughput is the training loop's image passes per second (from the
run's log) and per CPU-second of the whole run (the trainer and its loader, from the
operating system's accounting, so a busy machine changes it little, unless two runs'
threads contend for the same cores: waiting threads spin and count); the table shows the
second on the CPU and the first on a GPU, where the host's CPU time is its wall time.

The rows change one thing at a time from the paper's recipe (``--recipe paper``) at width 32
(the ``w32`` row; the ``paper`` rows keep the paper's width 64), then the project's recipe
with its cues and batch pinned (``shaderball``, :data:`SB`) and rows that change one thing
from it (``sb-*``); ``default`` is whatever ``trainer train`` trains by default. The paper's
loss adds VGG16 features, whose ImageNet weights these machines do not have: every
``paper`` row trains with its L1 ablation.

Every row's result is kept in its run folder (``--work``), so a run resumes and rows can be
added (a kept run, finished or not, trained with other settings than a row now asks for, as
when its recipe's defaults changed or ``--batch`` differs, is refused); the tables go to
``benchmarks/results/learning-R.json`` (``python -m benchmarks.report`` renders them into
docs/benchmarks.md), each row's picture grid (ground truth | network | |error| x 4) beside its
run, and a grid of ``--grid-rows`` side by side to ``docs/img/learning-R.png``.
"""

from __future__ import annotations

import argparse
import functools
import json
import os
import resource
import subprocess
import sys
import time
from pathlib import Path

from benchmarks.flops import count
from benchmarks.results import Table, save
from benchmarks.row_options import RESERVE, BadRowOption, Schedule, per_row, seconds
from farm.driver import submit
from farm.plan import JobConfig
from storage.catalog import Catalog
from storage.reader import Store
from storage.schema import RENDER_BITS
from trainer import runfiles
from trainer.cues import ordered
from trainer.precision import PRECISIONS, autocast_dtype
from trainer.training.config import TrainConfig, to_argv

BIN = Path(sys.executable).parent
CACHE = Path(__file__).resolve().parent / ".cache"
DOC_IMG = Path(__file__).resolve().parent.parent / "docs" / "img"
#: the store's materials (uniform, procedural), suns and samples per pixel
MATERIALS = (100, 100)
SUNS = 5
SPP = 32
HOLDOUT = 0.15
BUDGETS = (16_000, 64_000)
#: held-out samples shown in each grid
GRID_COUNT = 6
#: a row's run saves at an epoch's end once a minute at most: its epochs are short (17 steps
#: at batch 128 on a store of 500 materials) and a GPU trains one in less time than it takes
#: to write the run's checkpoint of up to 190 MB
CHECKPOINT_SECONDS = 60.0

#: the paper's recipe (L1: no VGG16 weights here), in the trainer's default precision, as
#: ``gpu.sh learn`` trains it beside the default
PAPER = {"recipe": "paper", "loss": "l1"}
#: the width-32 paper recipe the one-change rows start from (L1: no VGG16 weights here)
W32 = {"recipe": "paper", "loss": "l1", "width": 32, "precision": "fp32"}
#: the default recipe at its former width, and in fp32 as the CPU trained before bf16
DEFAULT_W32 = {"width": 32, "precision": "fp32"}
#: the sb-* rows' widest settings, each also run with another seed
W64_B4 = {"width": 64, "batch_size": 4}
W80_B4 = {"width": 80, "batch_size": 4}


#: the base of the ``sb-*`` rows (the ``shaderball`` row): the shaderball recipe with seven cues
#: (no ``ambient``) at batch 8 and width 32, in fp32, pinned here so that those rows keep what
#: they trained when the recipe's defaults move
SB = {
    "recipe": "shaderball", "batch_size": 8, "width": 32, "precision": "fp32",
    "inputs": ("paint", "geometry", "light", "normal", "reflection", "shadow", "shade"),
}  # fmt: skip


def with_cue(cue: str) -> dict:
    """The ``sb-*`` base with ``cue`` added to its cues (in their order)."""
    return SB | {"inputs": ordered((*SB["inputs"], cue))}


#: name: (what it changes, TrainConfig settings)
ROWS = {
    "paper": ("the paper's recipe: width 64, batch 6, Adam 1e-3 (the authors'), L1",
              PAPER),
    "paper-lr1e-2": ("the paper's recipe with its printed rate, 1e-2", PAPER | {"lr": 1e-2}),
    "w32": ("the paper's recipe at width 32: the rows below change one thing from it", W32),
    "w32-seed1": ("the w32 row with another seed: how far a row moves by chance",
                  W32 | {"seed": 1}),
    "onecycle": ("one-cycle schedule to 2e-3", W32 | {"lr_schedule": "onecycle", "lr": 2e-3}),
    "cosine": ("cosine schedule from 1e-3", W32 | {"lr_schedule": "cosine"}),
    "msssim": ("loss L1 + MS-SSIM", W32 | {"loss": "l1+msssim"}),
    "flip": ("loss L1 + LDR-FLIP", W32 | {"loss": "l1+flip"}),
    "groupnorm": ("GroupNorm", W32 | {"norm": "group"}),
    "batch16": ("batch 16", W32 | {"batch_size": 16}),
    "ema": ("weights averaged (0.999)", W32 | {"ema_decay": 0.999}),
    "paint": ("input: maps painted with the scene's parts", W32 | {"inputs": "paint"}),
    "geometry": ("input: normal, depth, part coverage", W32 | {"inputs": "geometry"}),
    "light": ("input: light as full-resolution planes", W32 | {"inputs": "light"}),
    "normal": ("input: shading normal, reflection", W32 | {"inputs": "normal,reflection"}),
    "shadow": ("input: sun visibility", W32 | {"inputs": "shadow"}),
    "shade": ("input: analytic shading", W32 | {"inputs": "shade"}),
    "residual": ("output: a correction of the analytic shading",
                 W32 | {"inputs": "shade", "residual": True}),
    "head": ("a full-resolution head", W32 | {"head": True}),
    "default": ("the default recipe (trainer.training.config.RECIPES: the sb-ambient-b4 row's "
                "settings at width 64), in the trainer's default precision", {}),
    "default-fp32": ("the default recipe in fp32", {"precision": "fp32"}),
    "default-w32": ("the default recipe at width 32, in fp32", DEFAULT_W32),
    "default-wd": ("the default-w32 row with decoupled weight decay 0.1 (AdamW)",
                   DEFAULT_W32 | {"weight_decay": 0.1}),
    "default-wd64": ("the default recipe with decoupled weight decay 0.1 (AdamW), in the "
                     "trainer's default precision", {"weight_decay": 0.1}),
    "default-lr3e-3": ("the default-w32 row with a peak rate of 3e-3", DEFAULT_W32 | {"lr": 3e-3}),
    "default-w48": ("the default recipe at width 48, in fp32",
                    {"width": 48, "precision": "fp32"}),
    "shaderball": ("the shaderball recipe with seven cues (no ambient) at batch 8: the sb-* "
                   "rows change one thing from it", SB),
    "sb-head": ("the shaderball row with a full-resolution head", SB | {"head": True}),
    "sb-l1": ("the shaderball row with an L1 loss", SB | {"loss": "l1"}),
    "sb-flip": ("the shaderball row with L1 + LDR-FLIP", SB | {"loss": "l1+flip"}),
    "sb-batch4": ("the shaderball row at batch 4", SB | {"batch_size": 4}),
    "sb-batch4-lr1e-3": ("the shaderball row at batch 4, the peak rate scaled with it",
                         SB | {"batch_size": 4, "lr": 1e-3}),
    "sb-batch32": ("the shaderball row at batch 32", SB | {"batch_size": 32}),
    "sb-batch32-lr8e-3": ("the shaderball row at batch 32, the peak rate scaled with it",
                          SB | {"batch_size": 32, "lr": 8e-3}),
    "sb-batch32-lr4e-3": ("the shaderball row at batch 32, the peak rate scaled with its root",
                          SB | {"batch_size": 32, "lr": 4e-3}),
    "sb-lr5e-3": ("the shaderball row with a peak rate of 5e-3", SB | {"lr": 5e-3}),
    "sb-glossy": ("the shaderball row with the glossy cue (the sky and floor in the specular "
                  "lobe)",
                  with_cue("glossy")),
    "sb-ambient": ("the shaderball row with the ambient cue (the sky's and the lit floor's "
                   "light)",
                   with_cue("ambient")),
    "sb-ambient-b4": ("the shaderball row with the ambient cue, at batch 4",
                      with_cue("ambient") | {"batch_size": 4}),
    "sb-ambient-b2": ("the shaderball row with the ambient cue, at batch 2",
                      with_cue("ambient") | {"batch_size": 2}),
    "sb-dec2": ("the shaderball row with two convolutions a decoder level",
                SB | {"decoder_convs": 2}),
    "sb-w48": ("the shaderball row at width 48", SB | {"width": 48}),
    "sb-w48-b4": ("the shaderball row at width 48 and batch 4",
                  SB | {"width": 48, "batch_size": 4}),
    "sb-w48-b2": ("the shaderball row at width 48 and batch 2",
                  SB | {"width": 48, "batch_size": 2}),
    "sb-w64-b4": ("the shaderball row at width 64 and batch 4", SB | W64_B4),
    "sb-w64-b2": ("the shaderball row at width 64 and batch 2",
                  SB | {"width": 64, "batch_size": 2}),
    "sb-w80-b4": ("the shaderball row at width 80 and batch 4", SB | W80_B4),
    "sb-w64-b4-seed1": ("the sb-w64-b4 row with another seed: how far it moves by chance",
                        SB | W64_B4 | {"seed": 1}),
    "sb-w80-b4-seed1": ("the sb-w80-b4 row with another seed: how far it moves by chance",
                        SB | W80_B4 | {"seed": 1}),
    "sb-seed1": ("the shaderball row with another seed: how far a row moves by chance",
                 SB | {"seed": 1}),
}  # fmt: skip


def ensure_store(resolution: int, cache: Path = CACHE) -> str:
    """The benchmark's store at ``resolution``, rendered by the farm on first use."""
    path = cache / f"learning-{resolution}.zarr"
    if (path / "zarr.json").exists():
        return str(path)

    uniform, procedural = MATERIALS
    print(f"rendering {path} ({sum(MATERIALS)} materials x {SUNS} suns, once)", flush=True)
    cfg = JobConfig(
        sources=(f"uniform:{uniform}", f"procedural:{procedural}"), out=str(path),
        resolution=resolution, samples=SPP, suns=SUNS, shard_size=5 * SUNS,
        ray_dashboard=False,
    )  # fmt: skip
    summary = submit(cfg, progress=True, echo=lambda *_: None)
    if not summary.ok:
        raise RuntimeError(f"the learning store failed: {summary.failed_materials}")
    return str(path)


#: how ``--lr-scale`` turns a row's batch ratio into a factor on its (peak) rate
LR_SCALES = {"none": lambda k: 1.0, "sqrt": lambda k: k**0.5, "linear": lambda k: k}


#: how a row's rate follows the batch given to every row, in the table's words
SCALED = {
    "none": "not scaled",
    "sqrt": "scaled by the square root of the ratio of that batch to its own",
    "linear": "scaled by the ratio of that batch to its own",
}


def rule(text: str) -> str:
    """``--lr-scale``'s value: one of :data:`LR_SCALES`."""
    if text not in LR_SCALES:
        raise ValueError(f"is not one of {', '.join(LR_SCALES)}")
    return text


def scale_rules(values: list[str], names: list[str]) -> dict[str, str]:
    """Each of the rows ``names``' ``LR_SCALES`` rule from ``--lr-scale`` values
    (:func:`benchmarks.row_options.per_row`); ``none`` where none is given."""
    return per_row("--lr-scale", values, names, ROWS, rule, "none")


def said_rules(rules: dict[str, str]) -> str:
    """The table's words for ``rules``: one rule for every row, or each row's."""
    if len(set(rules.values())) == 1:
        rule = next(iter(rules.values()))
        return "" if rule == "none" else f", each row's rate {SCALED[rule]}"
    return ", the rate of " + ", of ".join(f"{row} {SCALED[rule]}" for row, rule in rules.items())


def scaled_lr(name: str, store: str, batch: int, rule: str) -> float:
    """Row ``name``'s (peak) rate at ``batch``: its own rate times ``rule`` of the ratio of
    ``batch`` to its own batch (``linear``: Goyal et al. 2017's rule)."""
    own = TrainConfig(store=(store,), **ROWS[name][1])
    return own.lr * LR_SCALES[rule](batch / own.batch_size)


def steps_for(budget: int, batch: int, samples: int) -> int:
    """The fewest steps at ``batch`` that make at least ``budget`` image passes over a
    training split of ``samples``, each epoch's last batch short where ``batch`` does not
    divide ``samples`` (``budget // batch`` steps would fall short by those)."""
    epochs, rest = divmod(budget, samples)
    return max(1, epochs * -(-samples // batch) + -(-rest // batch))


@functools.cache
def training_samples(store: str, holdout_seed: int) -> int:
    """How many samples the trainer's split of ``store`` trains on (:data:`HOLDOUT` held out)."""
    return len(Catalog.snapshot([store], holdout_seed, HOLDOUT, None).split("train"))


def row_config(name: str, store: str, run: Path, budget: int, **run_as) -> TrainConfig:
    """The training run of row ``name`` for at least ``budget`` image passes; ``run_as``:
    settings of how it runs (``device``, ``preload``, ``workers``, ``batch_size`` for every
    row, ...)."""
    settings = ROWS[name][1] | run_as
    probe = TrainConfig(store=(store,), **settings)
    defaults = {"workers": 1, "log_every": 50}
    return TrainConfig(
        store=(store,), out=str(run),
        max_steps=steps_for(budget, probe.batch_size, training_samples(store, probe.holdout_seed)),
        epochs=100_000, holdout_fraction=HOLDOUT, val_samples=0, checkpoint_every=1_000_000,
        checkpoint_seconds=CHECKPOINT_SECONDS, keep=1, **(defaults | settings),
    )  # fmt: skip


class OtherSettings(ValueError):
    """A row's kept run (finished or not) was trained with other settings than asked for."""


#: the settings of how and where a run goes, not what it learns: a kept run may differ in them
#: (the precision a row trained in is in its result and its table)
HOW_IT_RUNS = frozenset((
    "store", "out", "resume", "device", "workers", "preload", "log_every", "checkpoint_every",
    "checkpoint_seconds",
    "keep", "log_samples", "val_every", "val_samples", "epochs", "precision", "time_limit",
))  # fmt: skip


def check_kept(run: Path, cfg: TrainConfig) -> None:
    """Raise :class:`OtherSettings` naming each setting in which the run ``run`` kept (its
    ``config.json``, written when it started) differs from ``cfg``, the one asked for now:
    a row's name and budget alone do not pin what it trains (its recipe's defaults, ``--batch``
    and ``--lr-scale`` change it)."""
    path = run / runfiles.CONFIG
    if not path.exists():
        return
    kept = TrainConfig.from_dict(json.loads(path.read_text())).to_dict()
    asked = cfg.to_dict()
    differ = [k for k in asked if k not in HOW_IT_RUNS and kept.get(k) != asked[k]]
    if differ:
        was = ", ".join(f"{k}={_shown(kept.get(k))}" for k in differ)
        now = ", ".join(f"{k}={_shown(asked[k])}" for k in differ)
        raise OtherSettings(f"{run} was trained with {was}, not {now}: give another --work "
                            "or remove that run")  # fmt: skip


def _shown(value) -> str:
    if isinstance(value, list):
        return ",".join(map(str, value)) or "none"
    return f"{value:g}" if isinstance(value, float) else str(value)


class Diverged(RuntimeError):
    """A row's training stopped on NaN or infinite values (its one-line error)."""


def train_row(cfg: TrainConfig) -> dict:
    """Run ``trainer train`` for ``cfg`` (resuming a run it left); the step it stopped at and
    its throughput. A resumed run's CPU time is this call's only, so it has no passes per
    CPU-second. Raises :class:`Diverged` for a run that diverged, ``CalledProcessError`` for
    any other end."""
    argv = [sys.executable, "-m", "trainer.cli", "train", *to_argv(cfg)]  # no installed script
    resumed = (Path(cfg.out) / runfiles.CHECKPOINTS).exists()
    if resumed:
        argv.append("--resume")
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    started = time.perf_counter()
    r = subprocess.run(argv, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    if r.returncode:
        last = (r.stderr.strip().splitlines() or [""])[-1]
        if "NaN/Inf" in last:
            raise Diverged(last.removeprefix("Error: "))
        sys.stderr.write(r.stderr[-3000:])
        r.check_returncode()
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    cpu = (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)
    steps = runfiles.kept_lines(runfiles.read_log(Path(cfg.out)))
    images = sum(x["images"] for x in steps)
    loop = runfiles.loop_seconds(steps)
    return {
        "steps": steps[-1]["step"] if steps else 0,
        "images": images,
        "passes_per_second": images / loop if loop else None,
        "passes_per_cpu_second": images / cpu if cpu and not resumed else None,
        "wall_seconds": time.perf_counter() - started,
    }


def score_run(run: Path, grid: Path | None = None, device: str = "cpu") -> dict:
    """The run's network on its held-out split, as ``trainer eval`` scores it."""
    from trainer.rendering.evaluate import score, test_split
    from trainer.rendering.load import load_renderer
    from trainer.scoring import write_grid

    renderer = load_renderer(run, device)
    split = test_split(renderer, None, None)
    scored = score([renderer], split, 16, GRID_COUNT)
    if grid is not None:
        write_grid(grid, scored.shown)
    return scored.summary()["overall"]


def result_file(work: Path, budget: int, name: str) -> Path:
    """Where row ``name`` at ``budget`` keeps its result in ``work``, once done
    (:func:`run_row`)."""
    return work / str(budget) / name / "result.json"


def run_row(name: str, store: str, work: Path, budget: int, **run_as) -> dict:
    """Row ``name`` at ``budget`` passes: trained and scored once, then read from its file. A
    row stopped by its time limit (``time_limit`` in ``run_as``) is scored where it stopped
    (``cut``) and not kept as done: the next call resumes it."""
    run = work / str(budget) / name
    done = result_file(work, budget, name)
    if done.exists():
        return json.loads(done.read_text())
    cfg = row_config(name, store, run, budget, **run_as)
    print(f"{name} ({budget:,} passes, {cfg.max_steps} steps of {cfg.batch_size})", flush=True)
    result = {"row": name, "budget": budget, "batch": cfg.batch_size, "lr": cfg.lr,
              "precision": precision_of(cfg)}  # fmt: skip
    try:
        speed = train_row(cfg)
    except Diverged as exc:  # a row's result too: this setting does not train
        result["diverged"] = str(exc)
        done.write_text(json.dumps(result, indent=1))
        print(f"  diverged: {exc}", flush=True)
        return result
    scores = score_run(run, run / "grid.png", run_as.get("device", "cpu"))
    result |= {**speed, **scores}
    # steps, not passes: an epoch's last batch may be short, so a run at its last step may
    # have trained a few passes under max_steps x batch
    if speed["steps"] < cfg.max_steps:
        result["cut"] = True
        print(f"  stopped by its time limit at {speed['images']:,} passes", flush=True)
    else:
        done.write_text(json.dumps(result, indent=1))
    print(f"  {said_scores(result)}", flush=True)  # in the log before any later row starts
    return result


def said_scores(result: dict) -> str:
    """A scored row's figures on one line, as its table row has them and how it trained."""
    low, high = result.get("psnr_low"), result.get("psnr_high")
    interval = f" [{low:.2f}, {high:.2f}]" if low is not None else ""
    speed = result.get("passes_per_second")
    return (
        f"{result['psnr']:.2f} dB{interval}, SSIM {result['ssim']:.4f}, FLIP "
        f"{result['flip']:.4f}; {result['steps']:,} steps, {result['images']:,} passes"
        + ("" if speed is None else f", {speed:.1f} passes/s")
    )


def precision_of(cfg: TrainConfig) -> str:
    """``bf16`` or ``fp32``: what the trainer autocasts ``cfg``'s steps to on this machine."""
    from trainer.devices import pick_device  # torch: the train extra

    return "bf16" if autocast_dtype(cfg.precision, pick_device(cfg.device).type) else "fp32"


def batch_of(result: dict) -> int:
    """A row's batch: as its result says, else as its settings make it (for the results
    written before they kept it)."""
    settings = ROWS[result["row"]][1]
    return result.get("batch") or TrainConfig(store=("-",), **settings).batch_size


def precision(result: dict) -> str:
    """The precision a row trained in; a result kept without one trained in fp32 (every run
    before bf16 autocast on the CPU was a CPU run)."""
    return result.get("precision", "fp32")


#: the speed column on each device: its title, the result's key and what the table says of it
SPEED = {
    "cpu": ("passes / CPU-s", "passes_per_cpu_second",
            "passes / CPU-s: of a run trained in one go (— for a resumed one); rows trained at "
            "different times met different loads on a shared machine"),
    # a GPU run's host process spins while it waits on the device: its CPU time is its wall
    "cuda": ("passes / s", "passes_per_second",
             "passes / s: the training loop's image passes a second on the GPU (from the run's "
             "log), without the set-up and the scoring"),
}  # fmt: skip


#: what the GPU table's TFLOP/s column counts (benchmarks.flops)
TFLOPS_SAID = "matrix and convolution work of forward, loss and backward: benchmarks.flops"


def tflops(result: dict, resolution: int) -> float | None:
    """The TFLOP/s a row's training loop sustained: its passes a second times the FLOPs of a
    pass at ``resolution`` (:mod:`benchmarks.flops`); None for a row without a speed."""
    speed = result.get("passes_per_second")
    if speed is None:
        return None
    try:
        flops = count(ROWS[result["row"]][1], resolution)["pass"]
    except Exception as exc:  # an aid to the table: a count that fails must not cost the table
        print(f"  {result['row']}: no TFLOP/s, the FLOP count failed ({exc})", flush=True)
        return None
    return round(speed * flops / 1e12, 1)


def table(resolution: int, budget: int, results: list[dict], about: str, device: str = "cpu"):
    """The rows' :class:`Table`; its speed column is the ``device``'s (:data:`SPEED`)."""
    speed, key, said = SPEED[device]
    t = Table(
        title=f"Learning per image pass: {resolution}², {budget:,} passes, held-out materials",
        columns=["row", "what changes", "batch", "precision", "PSNR dB", "95 % interval", "SSIM",
                 "FLIP", speed],
        notes=[about, said],
    )  # fmt: skip
    if device == "cuda":
        t.columns.append("TFLOP/s")
        t.notes.append(f"TFLOP/s: the passes a second times a pass's FLOPs ({TFLOPS_SAID})")
    for r in results:
        if "diverged" in r:
            t.rows.append([r["row"], ROWS[r["row"]][0], batch_of(r), precision(r), "diverged",
                           *[None] * (len(t.columns) - 5)])  # fmt: skip
            continue
        t.rows.append([
            r["row"], ROWS[r["row"]][0], batch_of(r), precision(r), round(r["psnr"], 2),
            f"{r['psnr_low']:.2f}-{r['psnr_high']:.2f}" if r.get("psnr_low") else None,
            round(r["ssim"], 4), round(r["flip"], 4),
            None if r.get(key) is None else round(r[key], 1),
        ])  # fmt: skip
        if device == "cuda":
            t.rows[-1].append(tflops(r, resolution))
        if r.get("cut"):
            t.notes.append(f"{r['row']}: stopped by its time limit after {r['images']:,} of "
                           f"{budget:,} passes, at a rate not yet annealed")  # fmt: skip
    return t


def side_by_side(work: Path, budget: int, names: list[str], path: Path, device: str) -> None:
    """One grid of the rows ``names`` on the same held-out samples."""
    from trainer.rendering.evaluate import score, test_split
    from trainer.rendering.load import load_renderer
    from trainer.scoring import write_grid

    renderers = [load_renderer(work / str(budget) / n, device) for n in names]
    scored = score(renderers, test_split(renderers[0], None, None), 16, GRID_COUNT)
    write_grid(path, scored.shown, labels=tuple(names))


def parser() -> argparse.ArgumentParser:
    """The command line of ``python -m benchmarks.learning``."""
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--resolution", type=int, default=64)
    p.add_argument("--budget", type=int, action="append", help="image passes (repeatable)")
    p.add_argument("--rows", default=None, help="comma-separated rows (default: every row)")
    p.add_argument("--grid-rows", default="paper,default")
    p.add_argument("--work", type=Path, default=CACHE / "learning")
    p.add_argument("--results", type=Path, default=None, help="folder of the result tables")
    p.add_argument("--store", default=None,
                   help="train on this store (one made as ensure_store makes it, carried to a "
                   "GPU machine, say) instead of the cached one")  # fmt: skip
    p.add_argument("--name", default=None, help="the table's name (default learning-R-Bk)")
    p.add_argument("--device", default="cpu", choices=["cpu", "cuda"])
    p.add_argument("--batch", type=int, default=None, help="every row's batch size")
    p.add_argument("--lr-scale", action="append", default=[], metavar="[ROW=]RULE",
                   help="with --batch: scale each row's (peak) rate by the ratio of --batch to "
                   "its own batch (linear), by its square root (sqrt) or not (none, the "
                   "default); ROW=RULE for one row (repeatable, e.g. --lr-scale sqrt "
                   "--lr-scale paper=none)")  # fmt: skip
    p.add_argument("--preload", action="store_true", help="trainer train --preload")
    p.add_argument("--precision", choices=PRECISIONS, default=None,
                   help="every row's trainer train --precision (default: each row's own, the "
                   "trainer's auto unless the row pins one)")  # fmt: skip
    p.add_argument("--row-seconds", action="append", default=[], metavar="[ROW=]SECONDS",
                   help="stop a row's training after this many seconds (trainer train "
                   "--time-limit) and score it there; the next call resumes it. SECONDS for "
                   "every row, ROW=SECONDS for one (repeatable, the later wins)")  # fmt: skip
    p.add_argument("--seconds", type=float, default=None,
                   help="the rows' wall-clock time in all, for a call with a limit of its "
                   "own: each row trains within what is left, less "
                   f"{RESERVE:g} s for it and each row after it (start-up and scoring) and "
                   "the --row-seconds of the rows after it; a row without --row-seconds "
                   "takes all the time the rows after it do not need: train it "
                   "last")  # fmt: skip
    p.add_argument("--note", action="append", default=[], help="a note for the table (repeatable)")
    return p


def checked(p: argparse.ArgumentParser, args: argparse.Namespace):
    """The rows ``args`` name, each row's rate rule and time cap; a bad setting ends the
    command through ``p.error`` (one line, exit 2) before anything trains."""
    names = args.rows.split(",") if args.rows else list(ROWS)
    if unknown := [n for n in names if n not in ROWS]:
        p.error(f"unknown row {unknown[0]!r}: one of {', '.join(ROWS)}")
    try:
        rules = scale_rules(args.lr_scale, names)
        caps = per_row("--row-seconds", args.row_seconds, names, ROWS, seconds)
    except BadRowOption as exc:
        p.error(str(exc))
    if args.seconds is not None and not args.seconds > 0:
        p.error(f"--seconds must be above 0, not {args.seconds:g}")
    if set(rules.values()) != {"none"} and args.batch is None:
        p.error("--lr-scale scales the rates to --batch: give --batch")
    return names, rules, caps


def run_settings(args: argparse.Namespace) -> dict:
    """What every row's run takes from the command line, beside its own settings."""
    run_as = {"device": args.device, "preload": args.preload}
    if args.batch is not None:
        run_as["batch_size"] = args.batch
    if args.precision is not None:
        run_as["precision"] = args.precision
    return run_as


def store_note(store: Store, args: argparse.Namespace, rules: dict) -> str:
    """The table's first note: the store, the held-out share and how every row trains."""
    layout, bits = store.layout, store.settings.get(RENDER_BITS)
    return (
        f"{layout.num_materials} materials (half uniform, half procedural) x "
        f"{layout.suns_per_material} suns"
        + ("" if bits is None else f" (renders kept at {bits} of float16's 10 mantissa bits)")
        + f", {HOLDOUT:.0%} of the materials held out; every row "
        + ("trains one CPU process" if args.device == "cpu" else "trains on one GPU")
        + (", the split in its memory" if args.preload else
           ", one loader worker" if args.device == "cpu" else "")
        + ("" if args.batch is None else f", batch {args.batch} for every row")
        + said_rules(rules)
    )  # fmt: skip


def grid_note(name: str, rows: list[str]) -> str:
    """The table's note that shows its grid, ``docs/img/NAME.png``, of ``rows``."""
    return (f"truth, {', '.join(rows)} and their errors on the same held-out samples: "
            f"![{name}](img/{name}.png)")  # fmt: skip


def publish(t: Table, name: str, results: list[dict], args, work: Path, budget: int) -> None:
    """Print and save the table ``name`` of ``results``, with the grid of ``--grid-rows``
    that trained (in ``--results``, or beside the docs' pictures)."""
    trained = {r["row"] for r in results if "diverged" not in r}
    shown = [n for n in args.grid_rows.split(",") if n in trained]
    if shown:
        grid = (args.results or DOC_IMG) / f"{name}.png"
        side_by_side(work, budget, shown, grid, args.device)
        print(f"grid: {grid}", flush=True)
        if args.results is None:  # the page docs/benchmarks.md shows it
            t.notes.append(grid_note(name, shown))
    print(t.markdown(), flush=True)
    save(name, t, *([args.results] if args.results else []))


def main(argv: list[str] | None = None) -> None:
    p = parser()
    args = p.parse_args(argv)
    started = time.monotonic()
    names, rules, caps = checked(p, args)
    store = args.store or ensure_store(args.resolution)
    opened = Store(store)
    layout = opened.layout
    work = args.work / str(layout.resolution)
    run_as = run_settings(args)
    os.environ.setdefault("OMP_NUM_THREADS", str(len(os.sched_getaffinity(0))))
    rates = {n: {"lr": scaled_lr(n, store, args.batch, rules[n])} if args.batch else {}
             for n in names}  # fmt: skip
    budgets = args.budget or BUDGETS
    try:  # every kept run, finished or not, before any row trains
        for budget, n in ((b, n) for b in budgets for n in names):
            run = work / str(budget) / n
            check_kept(run, row_config(n, store, run, budget, **run_as, **rates[n]))
    except OtherSettings as exc:
        p.error(str(exc))
    order = [(b, n) for b in budgets for n in names if not result_file(work, b, n).exists()]
    clock = Schedule(order, {(b, n): caps[n] for b, n in order}, args.seconds, started)
    for budget in budgets:
        results = [run_row(n, store, work, budget, **run_as, **rates[n],
                           time_limit=clock.limit((budget, n))) for n in names]  # fmt: skip
        t = table(layout.resolution, budget, results, store_note(opened, args, rules), args.device)
        if args.batch is not None:
            t.notes.append(f"(peak) rates at batch {args.batch}: " + ", ".join(
                f"{n} {rates[n]['lr']:.3g}" for n in names))  # fmt: skip
        t.notes += args.note
        name = args.name or f"learning-{layout.resolution}-{budget // 1000}k"
        publish(t, name, results, args, work, budget)


if __name__ == "__main__":
    main()
