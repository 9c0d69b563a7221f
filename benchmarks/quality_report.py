"""The quality comparison's measurements and report (``benchmarks.quality`` runs them).

Every score is against the test set's own renders, in the tonemapped display space the
networks predict (``trainer.rendering.evaluate.Tally``: PSNR, SSIM, FLIP), per material kind. A
baseline store must pair with the test set sample by sample (same materials, suns, Cycles
seeds), which is checked. Times are per frame on this machine: the networks through
``trainer.rendering.infer.Renderer`` at batch 1 (all threads), Cycles as one ``RenderProcess`` with
all threads, the whole render call (scene changes, path tracing, denoising, EXR out and in).
Measured times are kept in the work folder (``timings.json``) so a report is redone cheaply.

Each scored method keeps its per-sample scores (sorted by test sample, with each sample's
material; the networks' also as ``scores/NAME.csv`` in the work folder, as ``trainer eval
--per-sample`` writes them). From them the report gives each mean PSNR its 95 % interval
and each comparison it draws (ours less another method, on the same samples) its mean
difference with an interval: a bootstrap over whole materials (``trainer.intervals``).
"""

from __future__ import annotations

import csv
import datetime as dt
import json
import os
import platform
from pathlib import Path

import numpy as np
import torch
from PIL import Image, ImageDraw, ImageFont

from benchmarks import frame_times
from benchmarks.quality_plan import baseline_store, load_json, save_json
from benchmarks.store_renders import frames as store_frames
from benchmarks.store_renders import render_again, store_settings
from render_jobs.tonemap import to_uint8
from storage.backend import write_atomic
from storage.reader import Store
from trainer import checkpoint, runfiles
from trainer.intervals import (
    LEVEL,
    MIN_MATERIALS,
    RESAMPLES,
    bracket,
    cluster_mean,
    excludes_zero,
    paired_difference,
)
from trainer.model import count_parameters
from trainer.rendering.evaluate import evaluate
from trainer.rendering.infer import Renderer
from trainer.scoring import METRICS, Tally
from trainer.targets import Tonemap, light_vector

PAIRED = ("material_index", "sun_direction", "turbidity", "seed")


class QualityError(RuntimeError):
    pass


def _kinds(store: Store) -> dict[int, str]:
    return {m: rec["kind"] for m, rec in store.materials().items()}


def check_pairs(truth: Store, other: Store) -> None:
    """Raise unless ``other`` holds the same samples as ``truth`` (materials, suns, seeds)."""
    for store in (truth, other):
        if store.committed_shards() != list(range(store.layout.num_shards)):
            raise QualityError(f"{store.url}: not every shard is committed (render it first)")
    if truth.layout.num_samples != other.layout.num_samples:
        raise QualityError(f"{other.url}: {other.layout.num_samples} samples, not "
                           f"{truth.layout.num_samples}")  # fmt: skip
    for name in PAIRED:
        if not np.array_equal(truth.group[name][:], other.group[name][:]):
            raise QualityError(f"{other.url}: its {name} differs from {truth.url}'s")


def score_store(truth: Store, other: Store, tonemap: Tonemap, batch: int = 16) -> dict:
    """A baseline store's renders against the truth's, sample by sample: the means
    (:meth:`Tally.summary`) and ``per_sample`` (:func:`per_sample`)."""
    check_pairs(truth, other)
    kinds, tally = _kinds(truth), Tally()
    n = truth.layout.num_samples
    for lo in range(0, n, batch):
        ids = range(lo, min(lo + batch, n))
        target = tonemap(torch.from_numpy(np.stack([truth.render(i) for i in ids])))
        pred = tonemap(torch.from_numpy(np.stack([other.render(i) for i in ids])))
        names = [kinds[truth.layout.material_of_sample(i)] for i in ids]
        tally.add(pred, target, names)
    materials = [truth.layout.material_of_sample(i) for i in range(n)]
    return {**tally.summary(), "per_sample": per_sample(range(n), materials, tally.scores["all"])}


def per_sample(samples, materials, scores) -> dict:
    """Per-sample scores as a report row keeps them: ``{"sample", "material", "psnr",
    "ssim", "flip"}`` lists, sorted by sample; ``scores`` holds a ``(psnr, ssim, flip)`` a
    sample, in the order of ``samples``."""
    samples = np.asarray(list(samples), np.int64)
    order = np.argsort(samples, kind="stable")
    a = np.asarray(scores, np.float64).reshape(-1, 3)[order]
    return {
        "sample": samples[order].tolist(),
        "material": np.asarray(list(materials), np.int64)[order].tolist(),
        **{m: a[:, k].tolist() for k, m in enumerate(METRICS)},
    }


def read_sample_table(path: Path) -> dict:
    """:func:`per_sample` of the first model of a ``trainer eval --per-sample`` CSV file
    of one store."""
    with open(path, newline="") as f:
        rows = list(csv.DictReader(f))
    if len({r["store"] for r in rows}) > 1:
        raise QualityError(f"{path}: samples of more than one store")
    return per_sample(
        (int(r["sample"]) for r in rows),
        (int(r["material"]) for r in rows),
        [[float(r[f"{m}_1"]) for m in METRICS] for r in rows],
    )


def interval(row: dict, metric: str) -> dict | None:
    """The mean of ``metric`` over a row's samples with its interval
    (:func:`trainer.intervals.cluster_mean`); None for a row without per-sample scores."""
    ps = row.get("per_sample")
    return cluster_mean(ps[metric], ps["material"]) if ps else None


def paired(rows: dict, ours: str, other: str) -> dict | None:
    """``{metric: paired difference}`` of row ``ours`` less row ``other`` on the same
    samples (:func:`trainer.intervals.paired_difference`); None when either row has no
    per-sample scores."""
    a, b = rows[ours].get("per_sample"), rows[other].get("per_sample")
    if not a or not b:
        return None
    if a["sample"] != b["sample"]:
        raise QualityError(f"{ours} and {other} were scored on other samples")
    return {m: paired_difference(b[m], a[m], a["material"]) for m in METRICS}


# ---- reference renders ------------------------------------------------------------------


def reference_samples(store: Store, count: int) -> list[int]:
    """``count`` test samples, half of each kind (each material's first sun)."""
    kinds = _kinds(store)
    per = {k: [m for m, v in sorted(kinds.items()) if v == k] for k in sorted(set(kinds.values()))}
    share = max(1, count // max(1, len(per)))
    mats = sorted(m for ms in per.values() for m in ms[:share])[:count]
    return [m * store.layout.suns_per_material for m in mats]


def reference(plan) -> None:
    """Render the reference samples at ``reference_spp`` (kept in ``reference.npz``)."""
    s = plan.scale
    path = plan.work / "reference.npz"
    store = Store(plan.store("test"))
    samples = reference_samples(store, s.reference_count)
    if path.exists():
        with np.load(path) as z:
            if list(z["samples"]) == samples and int(z["spp"]) == s.reference_spp:
                return
    renders, seconds = render_again(store, samples, s.reference_spp, each_alone=True)
    arrays = {"samples": np.array(samples), "spp": s.reference_spp,
              "renders": renders, "seconds": seconds}  # fmt: skip
    write_atomic(path, lambda f: np.savez(f, **arrays))  # a killed run leaves no part of it


def score_reference(plan, tonemap: Tonemap) -> dict:
    """The ground truth's own renders against the reference renders."""
    store = Store(plan.store("test"))
    with np.load(plan.work / "reference.npz") as z:
        samples, ref = list(z["samples"]), z["renders"]
    kinds = _kinds(store)
    truth = np.stack([store.render(int(i)).astype(np.float32) for i in samples])
    tally = Tally()
    names = [kinds[store.layout.material_of_sample(int(i))] for i in samples]
    tally.add(tonemap(torch.from_numpy(truth)), tonemap(torch.from_numpy(ref)), names)
    return tally.summary()


# ---- times ----------------------------------------------------------------------------------


def network_ms(run: Path, store: Store, iters: int = 20) -> tuple[float, int]:
    """Median ms of one frame at batch 1 on the CPU (all threads), and the parameter count."""
    r = Renderer.from_checkpoint(run, "cpu")
    maps = torch.from_numpy(np.array(store.packed_maps(0)))[None]
    return frame_times.network_ms(r, maps, iters), count_parameters(r.model)


def cycles_ms(plan, samples: int, denoise: bool) -> float:
    """Median ms of a whole Cycles render call with all threads, over test samples (kept in
    ``timings.json``)."""
    key = f"cycles-{samples}spp{'-oidn' if denoise else ''}"
    path = plan.work / "timings.json"
    known = load_json(path)
    if key in known:
        return known[key]
    s = plan.scale
    store = Store(plan.store("test"))
    settings = store_settings(store, samples, denoise=denoise)
    frames = store_frames(store, reference_samples(store, s.timing_count + 1))
    ms = known[key] = frame_times.cycles_ms(settings, frames)
    save_json(path, known)
    return ms


# ---- the report -----------------------------------------------------------------------------


def measure(plan) -> dict:
    """Every score and time of the report, as plain data (kept as ``results.json``)."""
    s = plan.scale
    test, fixed = Store(plan.store("test")), Store(plan.store("test-fixed"))
    tonemap = Tonemap.from_dict(Renderer.from_checkpoint(plan.run("unet"), "cpu").state["tonemap"])
    rows = {}

    def net(name, on):
        table = plan.work / "scores" / f"{name}--{on}.csv"
        table.parent.mkdir(parents=True, exist_ok=True)
        result = evaluate(plan.run(name), on=[plan.store(on)], device="cpu", per_sample=table)
        ms, params = network_ms(plan.run(name), Store(plan.store(on)))
        return {**result, "per_sample": read_sample_table(table), "ms": ms, "parameters": params}

    rows["unet"] = net("unet", "test")
    rows["paper"] = net("paper", "test")
    rows["unet-noskips"] = net("unet-noskips", "test")
    for spp in s.baselines:
        for oidn in (False, True):
            name = baseline_store(spp, oidn)
            rows[name] = {**score_store(test, Store(plan.store(name)), tonemap),
                          "ms": cycles_ms(plan, spp, oidn)}  # fmt: skip
    rows["truth"] = {"ms": cycles_ms(plan, s.samples, False)}
    rows["zf-fixed"] = net("zf-fixed", "test-fixed")
    rows["unet-fixed"] = net("unet-fixed", "test-fixed")
    rows["unet-on-fixed"] = net("unet", "test-fixed")
    rows["fixed-2spp-oidn"] = {
        **score_store(fixed, Store(plan.store("test-fixed-2spp-oidn")), tonemap),
        "ms": cycles_ms(plan, 2, True),
    }
    rows["reference"] = score_reference(plan, tonemap)
    return rows


def write(plan, scale_name: str, doc: Path, img: Path) -> None:
    """Measure, then write ``doc`` (markdown) and ``img`` (the picture grid)."""
    rows = measure(plan)
    (plan.work / "results.json").write_text(json.dumps(rows, indent=1, default=str))
    picture_grid(plan, img)
    doc.parent.mkdir(parents=True, exist_ok=True)
    doc.write_text(markdown(plan, scale_name, rows, img, doc))
    print(f"wrote {doc} and {img}", flush=True)


def _fmt(m: dict | None, key: str, digits: int) -> str:
    if not m or m.get(key) is None:
        return "—"
    return f"{m[key]:.{digits}f}"


def _metrics(m: dict | None) -> str:
    return f"{_fmt(m, 'psnr', 2)} | {_fmt(m, 'ssim', 4)} | {_fmt(m, 'flip', 4)}"


def _scores(row: dict) -> str:
    """A scored row's table cells: PSNR, its interval, SSIM, FLIP."""
    o = row["overall"]
    return (f"{_fmt(o, 'psnr', 2)} | {_interval(interval(row, 'psnr'), '.2f')} | "
            f"{_fmt(o, 'ssim', 4)} | {_fmt(o, 'flip', 4)}")  # fmt: skip


def _interval(d: dict | None, fmt: str) -> str:
    return bracket(None, None) if d is None else bracket(d["low"], d["high"], fmt)


def _difference(d: dict, fmt: str) -> str:
    """A paired difference as a cell: its mean, and its interval where it has one."""
    ci = "" if d["low"] is None else " " + _interval(d, fmt)
    return f"{d['mean']:{fmt}}{ci}"


LEVEL_TEXT = f"{LEVEL * 100:g} %"
DIFF_FORMATS = ("+.2f", "+.4f", "+.4f")  # PSNR, SSIM, FLIP


def difference_table(rows: dict, ours: str, title: str, others: list[tuple[str, str]]):
    """Markdown lines: row ``ours`` less each of ``others`` (``(label, key)``) on the same
    samples, with intervals (:func:`paired`); none when a row has no per-sample scores."""
    lines = [f"| {title} less | PSNR dB | SSIM | FLIP | ours higher PSNR on |",
             "|---|---|---|---|---|"]  # fmt: skip
    for label, key in others:
        d = paired(rows, ours, key)
        if d is None:
            return []
        cells = [_difference(d[m], f) for m, f in zip(METRICS, DIFF_FORMATS, strict=True)]
        lines.append(f"| {label} | " + " | ".join(cells) + f" | {d['psnr']['higher']:.0%} |")
    return lines


def intervals_text(rows: dict, ours: str) -> str:
    """What the intervals are, for the report."""
    ps = rows[ours]["per_sample"]
    return (
        f"Each mean is over {len(ps['sample'])} samples of "
        f"{len(set(ps['material']))} materials. The intervals are {LEVEL_TEXT} intervals of a "
        f"bootstrap that resamples whole materials ({RESAMPLES} resamples, seed 0; "
        "`trainer.intervals`), since a material's suns are not independent draws. Each "
        "difference below is ours less the other method, sample by sample on the same "
        "samples; FLIP is lower for the better, so a negative FLIP difference favours ours. "
        "An interval that holds 0 is a difference this test set cannot show; under "
        f"{MIN_MATERIALS} materials there are no intervals."
    )


def markdown(plan, scale_name: str, rows: dict, img: Path, doc: Path) -> str:
    """The report: its sections in order, as markdown."""
    cpu = f"{platform.processor() or platform.machine()}, {torch.get_num_threads()} threads"
    out = [
        "# What the renderer is worth",
        "",
        f"The paper's Table 1 reproduced on this machine ({dt.date.today()}, scale "
        f"`{scale_name}`), by `make quality` (`python -m benchmarks.quality`; the module "
        "docstring says what each step does). Every score is on **held-out materials only**: "
        "a test set rendered from the same sources with another seed, so none of its "
        "materials was trained on. Scores are against the test set's own Cycles renders, in "
        "the networks' tonemapped display space; FLIP is NVIDIA's perceptual difference (0 is "
        "identical, lower is better).",
        "",
        *_data_section(plan, rows, cpu),
        "",
        *_random_suns_section(plan.scale, rows, cpu),
        "",
        *_fixed_sun_section(rows),
        "",
        *_reference_section(plan.scale, rows["reference"]),
        "",
        *_pictures_section(img, doc),
    ]
    return "\n".join(out)


def _recipe(plan) -> str:
    """What the ``unet`` run trained, from its config: the settings a recipe gives."""
    c = json.loads((plan.run("unet") / runfiles.CONFIG).read_text())
    cues = ", ".join(c["inputs"]) or "none"
    average = f"a weight average ({c['ema_decay']})" if c["ema_decay"] else "no weight average"
    return (f"`--recipe {c['recipe']}`, width {c['width']}, scene cues {cues}, {c['norm']} "
            f"norm, loss {c['loss']}, batch {c['batch_size']}, Adam {c['lr']:g} "
            f"{c['lr_schedule']}, {average}")  # fmt: skip


def _precisions(plan) -> str:
    """How the runs multiplied, from their last checkpoints (``--precision auto`` resolves
    to bf16 on a CPU with bf16 units, fp32 on one without)."""
    got: dict[str, list[str]] = {}
    for name, _, _ in plan.trainings():
        last = checkpoint.load(checkpoint.latest(plan.run(name)))
        got.setdefault(last.get("precision") or "fp32", []).append(name)
    return "; ".join(f"{p} ({', '.join(names)})" for p, names in got.items())


def _data_section(plan, rows: dict, cpu: str) -> list[str]:
    s = plan.scale
    train, test = Store(plan.store("train")), Store(plan.store("test"))
    runs = [name for name, _, _ in plan.trainings()]
    seconds = {n: runfiles.loop_seconds(runfiles.read_log(plan.run(n))) for n in runs}
    steps = {n: rows[n].get("checkpoint_step") for n in rows if "checkpoint_step" in rows[n]}
    return [
        "## Data and training",
        "",
        f"- training set: {train.layout.num_materials} materials "
        f"({', '.join(f'{v} {k}' for k, v in _count(train).items())}) x {s.suns} random suns "
        f"= {train.layout.num_samples} renders at {s.resolution}², {s.samples} spp "
        "(Hosek-Wilkie sky, turbidity 2-10);",
        f"- test set: {test.layout.num_materials} other materials "
        f"({', '.join(f'{v} {k}' for k, v in _count(test).items())}) x {s.suns} suns = "
        f"{test.layout.num_samples} renders, same settings, seed 1;",
        f"- fixed-sun sets (Zsolnai-Fehér has no light input): {s.fixed[0]} / {s.fixed[1]} "
        "uniform materials under one sun (direction (-0.4, -0.6, 0.7), turbidity 3);",
        f"- training, one CPU process ({cpu}): ours is the shaderball recipe (docs/training.md) "
        f"with the settings its run recorded: {_recipe(plan)}; "
        f"{s.epochs} epochs on the training set and {s.fixed_epochs} on the fixed-sun set; "
        f"the paper's U-Net (`--recipe paper` with its L1 loss: Adam lr 1e-3, batch {s.batch}, "
        f"U-Nets {s.width} channels wide at their first level"
        f"{'' if s.width == 64 else ' (the paper: 64)'}) {s.paper_epochs} epochs, and "
        f"Zsolnai-Fehér {s.fixed_epochs}. Steps and time in the step loop (from each run's log): "
        + ", ".join(
            f"{n} {steps.get(n, '?')} steps / {seconds.get(n, 0) / 60:.0f} min"
            for n in ("unet", "paper", "unet-noskips", "unet-fixed", "zf-fixed")
        )
        + f". Precision (`--precision auto`; weights and losses fp32): {_precisions(plan)}.",
        "- these are short runs, what one session on 2 CPU cores fits, far from the paper's "
        "training; the pictures show how far from converged. Raise the scale's epochs in "
        "`benchmarks/quality_plan.py` and rerun: training resumes from the last checkpoint.",
        "- not trained: the paper's L1 + VGG16 loss. No ImageNet VGG16 weights are available on "
        "these machines; `--loss l1+vgg` works for users who have them (`--vgg-weights`).",
    ]


def _random_suns_section(s, rows: dict, cpu: str) -> list[str]:
    """The main table, the findings, the scores per material kind and the differences."""
    named = [
        ("ours (the shaderball recipe)", "unet"),
        ("the paper's U-Net (L1)", "paper"),
        ("the paper's U-Net without skips (L1)", "unet-noskips"),
    ]
    named += [(label, key) for key, label in cycles_baselines(s.baselines).items()]
    out = [
        "## Held-out materials, random suns",
        "",
        f"ms / frame on this machine's CPU ({cpu}), batch 1; no GPU was available for this "
        "run. Cycles times are whole render calls (scene changes, path tracing, denoising, "
        "EXR). Each time is taken at its step of the run, so days apart for a run that spans "
        "sessions; `make bench-frames` re-times every method side by side in one run.",
        "",
        f"| method | PSNR dB | PSNR {LEVEL_TEXT} interval | SSIM | FLIP | ms / frame |",
        "|---|---|---|---|---|---|",
    ]
    for label, key in named:
        out.append(f"| {label} | {_scores(rows[key])} | {rows[key]['ms']:.1f} |")
    out.append(f"| Cycles {s.samples} spp (the ground truth itself) | — | — | — | — | "
               f"{rows['truth']['ms']:.1f} |")  # fmt: skip
    out += ["", "Where the network wins and where it does not:", ""]
    out += findings(rows, s.baselines, s.reference_spp)
    out += ["", "Per material kind:", ""]
    kinds = sorted(rows["unet"]["by_kind"])
    out.append("| method | " + " | ".join(f"{k} PSNR / SSIM / FLIP" for k in kinds) + " |")
    out.append("|---|" + "---|" * len(kinds))
    for label, key in named:
        bk = rows[key]["by_kind"]
        cells = [f"{_fmt(bk.get(k), 'psnr', 2)} / {_fmt(bk.get(k), 'ssim', 3)} / "
                 f"{_fmt(bk.get(k), 'flip', 3)}" for k in kinds]  # fmt: skip
        out.append(f"| {label} | " + " | ".join(cells) + " |")
    differences = difference_table(rows, "unet", named[0][0], named[1:])
    if differences:
        out += ["", "### How sure the differences are", "", intervals_text(rows, "unet"), "",
                *differences]  # fmt: skip
    return out


def _fixed_sun_section(rows: dict) -> list[str]:
    out = [
        "## Fixed sun, uniform materials (the Zsolnai-Fehér et al. 2018 comparison)",
        "",
        f"| method | PSNR dB | PSNR {LEVEL_TEXT} interval | SSIM | FLIP | ms / frame | "
        "parameters |",
        "|---|---|---|---|---|---|---|",
    ]
    fixed_rows = [
        ("Zsolnai-Fehér (assumed layers, `trainer/zf.py`)", "zf-fixed"),
        ("ours, trained on the same fixed-sun data", "unet-fixed"),
        ("ours, trained on random suns (the main run)", "unet-on-fixed"),
    ]
    for label, key in fixed_rows:
        m = rows[key]
        out.append(f"| {label} | {_scores(m)} | {m['ms']:.1f} | "
                   f"{m['parameters'] / 1e6:.1f} M |")  # fmt: skip
    m = rows["fixed-2spp-oidn"]
    out.append(f"| Cycles 2 spp + OIDN | {_scores(m)} | {m['ms']:.1f} | — |")
    others = [fixed_rows[0], fixed_rows[2], ("Cycles 2 spp + OIDN", "fixed-2spp-oidn")]
    differences = difference_table(rows, "unet-fixed", "ours, trained on the fixed sun,", others)
    return out + (["", *differences] if differences else [])


def _reference_section(s, ref: dict) -> list[str]:
    out = [
        "## How converged the ground truth is",
        "",
        f"{ref['overall']['n']} test samples rendered again at {s.reference_spp} spp: the "
        f"ground truth ({s.samples} spp) against them. No score against the ground truth can "
        "mean more than this.",
        "",
        "| | n | PSNR dB | SSIM | FLIP |",
        "|---|---|---|---|---|",
    ]
    for kind, m in [("all", ref["overall"]), *ref["by_kind"].items()]:
        out.append(f"| ground truth vs {s.reference_spp} spp, {kind} | {m['n']} | {_metrics(m)} |")
    return out


def _pictures_section(img: Path, doc: Path) -> list[str]:
    rel = os.path.relpath(Path(img).resolve(), doc.resolve().parent)
    return [
        "## Pictures",
        "",
        "Uniform materials under the fixed sun (every method), then procedural ones under "
        "random suns (Zsolnai-Fehér renders only the fixed sun). The error column is "
        "|ours - ground truth| x 4.",
        "",
        f"![ground truth, ours, 2 spp + OIDN, Zsolnai-Fehér, error]({rel})",
        "",
    ]


def _cheapest(rows: dict, keys: list[str], good) -> str | None:
    """The fastest of ``keys`` whose overall scores pass ``good``, or None."""
    passing = [k for k in keys if good(rows[k]["overall"])]
    return min(passing, key=lambda k: rows[k]["ms"]) if passing else None


def cycles_baselines(baselines: tuple[int, ...]) -> dict[str, str]:
    """``{store name: label}`` of the Cycles baselines, raw then OIDN for each spp."""
    return {
        baseline_store(spp, oidn): f"Cycles {spp} spp{' + OIDN' if oidn else ''}"
        for spp in baselines
        for oidn in (False, True)
    }


def findings(rows: dict, baselines: tuple[int, ...], reference_spp: int) -> list[str]:
    """Plain sentences on where the network wins and where it does not, from the numbers;
    each comparison with its paired difference where the rows have per-sample scores."""
    ours = rows["unet"]
    o, ms = ours["overall"], ours["ms"]
    labels = cycles_baselines(baselines)
    keys = list(labels)
    fastest = min(keys, key=lambda k: rows[k]["ms"])
    out = [
        f"- Time: ours renders a frame in {ms:.1f} ms; the fastest Cycles frame here "
        f"({labels[fastest]}) takes {rows[fastest]['ms']:.1f} ms, "
        f"{rows[fastest]['ms'] / ms:.1f}x ours."
    ]
    for metric, name, good in (
        ("psnr", "PSNR", lambda m: m["psnr"] >= o["psnr"]),
        ("flip", "FLIP", lambda m: m["flip"] <= o["flip"]),
    ):
        best = _cheapest(rows, keys, good)
        pick = max if metric == "psnr" else min
        if best is None:
            top = pick(keys, key=lambda k: rows[k]["overall"][metric])
            line = (
                f"- {name}: no Cycles setting measured reaches ours ({o[metric]:.4g}); the best, "
                f"{labels[top]}, scores {rows[top]['overall'][metric]:.4g}"
                f"{_against(rows, top, metric)}."
            )
        else:
            b = rows[best]
            line = (
                f"- {name}: ours scores {o[metric]:.4g}; the cheapest Cycles setting at least as "
                f"good is {labels[best]} ({b['overall'][metric]:.4g}) at {b['ms']:.1f} ms a "
                f"frame, {b['ms'] / ms:.1f}x ours{_against(rows, best, metric)}."
            )
        under = [k for k in keys if not good(rows[k]["overall"])]
        if best is not None and under:
            near = pick(under, key=lambda k: rows[k]["overall"][metric])
            line += (
                f" The closest setting under ours is {labels[near]} "
                f"({rows[near]['overall'][metric]:.4g}){_against(rows, near, metric)}."
            )
        out.append(line)
    zf, same = rows["zf-fixed"], rows["unet-fixed"]
    out.append(
        f"- Fixed sun: ours trained on the same data scores {same['overall']['psnr']:.2f} dB "
        f"against Zsolnai-Fehér's {zf['overall']['psnr']:.2f} dB"
        f"{_against(rows, 'zf-fixed', 'psnr', ours='unet-fixed')}, with "
        f"{same['parameters'] / 1e6:.1f} M parameters against {zf['parameters'] / 1e6:.1f} M."
    )
    ref = rows["reference"]["overall"]
    out.append(
        f"- Ceiling: the ground truth itself is {ref['psnr']:.2f} dB from {reference_spp} spp, "
        f"so ours at {o['psnr']:.2f} dB is {ref['psnr'] - o['psnr']:.2f} dB under what any "
        "method could show against it."
    )
    return out


def _against(rows: dict, other: str, metric: str, ours: str = "unet") -> str:
    """``; ours less it: D [low, high], ...`` for a finding, or nothing without per-sample
    scores."""
    d = paired(rows, ours, other)
    if d is None:
        return ""
    d = d[metric]
    text = f"; ours less it: {_difference(d, DIFF_FORMATS[METRICS.index(metric)])}"
    text += " dB" if metric == "psnr" else ""
    if d["low"] is None:
        return text
    if excludes_zero(d):
        return text + " (the interval excludes 0)"
    return text + " (the interval holds 0: this test set cannot tell them apart)"


def _count(store: Store) -> dict[str, int]:
    from collections import Counter

    return dict(sorted(Counter(_kinds(store).values()).items()))


# ---- the picture grid -------------------------------------------------------------------

#: column labels (ASCII: PIL's default font has no accented letters)
GRID_COLUMNS = ("ground truth", "ours", "2 spp + OIDN", "Zsolnai-Feher", "|ours - truth| x 4")
GRID_MIN_TILE = 256


def picture_grid(plan, path: Path, rows_per_set: int = 3) -> None:
    """Rows of uniform materials under the fixed sun, then procedural ones under random
    suns: ground truth | ours | 2 spp + OIDN | Zsolnai-Fehér | error, labelled."""
    ours = Renderer.from_checkpoint(plan.run("unet"), "cpu")
    zf = Renderer.from_checkpoint(plan.run("zf-fixed"), "cpu")
    tonemap = ours.tonemap
    rows = []
    for truth_name, oidn_name, kind, with_zf in [
        ("test-fixed", "test-fixed-2spp-oidn", "uniform", True),
        ("test", "test-2spp-oidn", "procedural", False),
    ]:
        truth = Store(plan.store(truth_name))
        oidn = Store(plan.store(oidn_name)) if Path(plan.store(oidn_name)).exists() else None
        kinds = _kinds(truth)
        picks = [m for m, k in sorted(kinds.items()) if k == kind][:rows_per_set]
        for m in picks:
            i = m * truth.layout.suns_per_material
            maps = torch.from_numpy(np.array(truth.packed_maps(m)))[None]
            light = torch.from_numpy(light_vector(*truth.light(i))[None])
            gt = tonemap(torch.from_numpy(truth.render(i).astype(np.float32))[None])[0]
            pred = ours.render_batch(maps, light)[0]
            cells = [gt, pred]
            cells.append(tonemap(torch.from_numpy(oidn.render(i).astype(np.float32))[None])[0]
                         if oidn is not None else None)  # fmt: skip
            cells.append(zf.render_batch(maps, light)[0] if with_zf else None)
            cells.append(((pred - gt).abs().mean(0, keepdim=True) * 4).clamp(0, 1))
            rows.append(cells)
    size = plan.scale.resolution
    factor = max(1, -(-GRID_MIN_TILE // size))
    tile, header = size * factor, 26
    grid = Image.new("RGB", (tile * len(GRID_COLUMNS), header + tile * len(rows)), (24, 24, 24))
    draw, font = ImageDraw.Draw(grid), ImageFont.load_default(size=15)
    for j, name in enumerate(GRID_COLUMNS):
        draw.text((j * tile + 6, 5), name, fill=(235, 235, 235), font=font)
    for r, cells in enumerate(rows):
        for j, cell in enumerate(cells):
            x, y = j * tile, header + r * tile
            if cell is None:
                draw.text((x + tile // 3, y + tile // 2), "fixed sun only", fill=(140, 140, 140),
                          font=font)  # fmt: skip
                continue
            pic = to_uint8(cell.detach().cpu().numpy()).repeat(factor, 0).repeat(factor, 1)
            grid.paste(Image.fromarray(pic), (x, y))
    path.parent.mkdir(parents=True, exist_ok=True)
    grid.save(path)
