"""Several checkpoints scored on the same held-out samples, and how sure their differences are.

``trainer eval --checkpoint A --checkpoint B ...`` runs every model on each batch it reads
(:func:`trainer.rendering.evaluate.score`), so the scores are paired: per sample, B's PSNR less A's.
The samples of one material (its suns) are not independent draws, so the confidence
interval of a mean difference resamples whole materials (a cluster bootstrap):
:func:`trainer.intervals.paired_difference`. The first checkpoint is the one the others are
compared with.

Models compare only on samples none of them trained on, against the same targets: every
model is scored on the first one's held-out samples, and each of the others must not have
trained on any of their materials (by ``source_id``, as its checkpoint names them). So runs
that hold out the same samples compare (one ``--holdout-seed`` and ``--holdout-fraction`` on
one set of stores, whatever their ``--seed``), and so do a network and one fine-tuned from it
(``--init`` keeps the first run's held-out materials held out), either way round. With
``--on`` every model is scored on the other stores' samples, checked against each one. The
models must share a tonemap.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
from tabulate import tabulate

from storage.reader import Store
from trainer.intervals import LEVEL, MIN_MATERIALS, bracket, paired_difference
from trainer.rendering.evaluate import (
    EvalError,
    NoCatalog,
    score,
    test_split,
    trained_on_is_checked,
    trained_sources,
    write_sample_table,
)
from trainer.rendering.load import load_renderer
from trainer.samples import samples_digest
from trainer.scoring import METRICS, write_grid


def labels(names: list[str], weights: list[str]) -> list[str]:
    """What each model is called: its name as given, and its weights where two names are
    the same."""
    return [f"{n} ({w})" if names.count(n) > 1 else n for n, w in zip(names, weights, strict=True)]


def compare(
    ckpts: list[str],
    weights: list[str],
    stores: list[str] | None = None,
    batch_size: int = 8,
    grid: Path | None = None,
    grid_count: int = 4,
    device: str = "auto",
    on: list[str] | None = None,
    per_sample: Path | None = None,
) -> dict:
    """Scores of the models ``ckpts`` (each with its ``weights``) on the same samples, and of
    each after the first against the first (:func:`paired_difference` of PSNR, SSIM and
    FLIP); a grid of ``grid_count`` samples spread over them (ground truth, each model,
    each error) to ``grid`` when given, and every sample's scores to the CSV file
    ``per_sample`` (:func:`trainer.rendering.evaluate.write_sample_table`)."""
    renderers, splits = [], []
    for i, (ckpt, w) in enumerate(zip(ckpts, weights, strict=True)):
        renderer = load_renderer(ckpt, device, w)
        try:
            if i == 0 or on:  # each model's check of the --on stores
                splits.append(test_split(renderer, stores, on))
        except (NoCatalog, EvalError) as exc:
            raise type(exc)(f"{ckpt}: {exc}") from None
        renderers.append(renderer)
    split = splits[0]
    _comparable(ckpts, renderers, split, stores, on)
    scored = score(renderers, split, batch_size, grid_count)
    names = labels(list(ckpts), [r.weights for r in renderers])
    groups = np.array(scored.materials, np.int64).reshape(-1, 2)
    rows = [np.array(t.scores["all"], np.float64) for t in scored.tallies]
    models = [
        _model_entry(ckpt, name, renderer, scored.summary(i), on)
        for i, (ckpt, name, renderer) in enumerate(zip(ckpts, names, renderers, strict=True))
    ]
    for model, row in zip(models[1:], rows[1:], strict=True):
        model["vs_first"] = {
            m: paired_difference(rows[0][:, k], row[:, k], groups) for k, m in enumerate(METRICS)
        }
    result = {
        "samples": len(split),
        "materials": len(np.unique(groups, axis=0)),
        "heldout_set": samples_digest(split, np.arange(len(split))),
        "on": list(on) if on else None,
        "level": LEVEL,
        "models": models,
    }
    if grid is not None and scored.shown:
        write_grid(grid, scored.shown, labels=tuple(names))
        result["grid"] = str(grid)
    if per_sample is not None:
        write_sample_table(per_sample, split, scored)
        result["per_sample"] = str(per_sample)
    return result


def _model_entry(ckpt, label: str, renderer, summary: dict, on) -> dict:
    """One model's part of :func:`compare`'s result (before its differences): its
    ``summary`` (:meth:`trainer.rendering.evaluate.Scored.summary`) and where it comes from."""
    return {
        "checkpoint": str(ckpt),
        "label": label,
        "checkpoint_step": renderer.step,
        "runtime": renderer.runtime,
        "weights": renderer.weights,
        "on_checked_against_run": trained_on_is_checked(renderer) if on else None,
        **summary,
    }


def report(result: dict) -> str:
    """:func:`compare`'s result as text: each model's scores, PSNR by material kind, and
    each model after the first against the first."""
    models = result["models"]
    few = result["materials"] < MIN_MATERIALS
    where = "samples of the --on stores" if result["on"] else "held-out samples"
    rows = [
        [i, m["label"], m["checkpoint_step"], o["psnr"], bracket(o["psnr_low"], o["psnr_high"]),
         o["ssim"], o["flip"]]
        for i, m in enumerate(models, 1) for o in [m["overall"]]
    ]  # fmt: skip
    kinds = [
        [k, first["n"], *(m["by_kind"][k]["psnr"] for m in models)]
        for k, first in models[0]["by_kind"].items()
    ]
    lines = [
        f"{result['samples']} {where} of {result['materials']} materials (set "
        f"{result['heldout_set']}{'' if result['on'] else ', held out by 1'}), every model "
        "on the same ones",
        tabulate(
            rows,
            ["", "checkpoint", "step", "PSNR dB", "95 % interval", "SSIM", "FLIP"],
            floatfmt=("", "", "", ".2f", "", ".4f", ".4f"),
        ),  # fmt: skip
        "",
        "PSNR dB by material kind",
        tabulate(kinds, ["kind", "n", *range(1, len(models) + 1)], floatfmt=".2f"),
        "",
        f"against 1: mean difference [{result['level']:.0%} interval, a bootstrap over "
        "materials]; FLIP: lower is better"
        + (f" (no intervals: fewer than {MIN_MATERIALS} materials)" if few else ""),
        tabulate(*_difference_table(models), disable_numparse=True),
    ]
    if "grid" in result:
        lines.append(f"grid: {result['grid']}")
    if "per_sample" in result:
        lines.append(f"each sample's scores: {result['per_sample']}")
    return "\n".join(lines)


def _difference_table(models: list[dict]) -> tuple[list[list], list[str]]:
    """Rows and header of each model after the first against the first: the mean
    difference of each score and its interval, and the share of samples where its PSNR is
    the higher."""
    rows = []
    for i, m in enumerate(models[1:], 2):
        row = [i]
        for metric, fmt in (("psnr", "+.2f"), ("ssim", "+.4f"), ("flip", "+.4f")):
            d = m["vs_first"][metric]
            ci = "" if d["low"] is None else f" [{d['low']:{fmt}}, {d['high']:{fmt}}]"
            row.append(f"{d['mean']:{fmt}}{ci}")
        rows.append([*row, f"{m['vs_first']['psnr']['higher']:.0%}"])
    return rows, ["", "PSNR dB", "SSIM", "FLIP", "higher PSNR on"]


def split_sources(split) -> set[str]:
    """The ``source_id`` of every material in ``split``."""
    out = set()
    for s, url in enumerate(split.urls):
        store = Store(url, split.storage_options)
        records = store.materials()
        samples = split.refs[split.refs[:, 0] == s, 1].tolist()
        out |= {records[store.layout.material_of_sample(k)]["source_id"] for k in samples}
    return out


def _comparable(ckpts, renderers, split, stores, on) -> None:
    """An :class:`EvalError` naming the first model after the first that trained on a
    material of ``split`` (the first's held-out samples; the ``--on`` stores were checked
    by :func:`test_split`), or that renders against another tonemap."""
    scored = None
    for ckpt, renderer in zip(ckpts[1:], renderers[1:], strict=True):
        if renderer.tonemap != renderers[0].tonemap:
            other, base = (f"{t.curve} at exposure {t.exposure:g}"
                           for t in (renderer.tonemap, renderers[0].tonemap))  # fmt: skip
            raise EvalError(
                f"{ckpt}: trained against another tonemap than {ckpts[0]} ({other}, not "
                f"{base}): their scores do not compare"
            )
        if on:
            continue
        if not trained_on_is_checked(renderer):
            raise NoCatalog(
                f"{ckpt}: the model names no stores of its run (exported --no-catalog), so the "
                f"materials it trained on are unknown: compare --on a store none trained on"
            )
        scored = split_sources(split) if scored is None else scored
        try:
            seen = sorted(scored & trained_sources(renderer, stores))
        except EvalError as exc:
            raise EvalError(f"{ckpt}: {exc}") from None
        if seen:
            raise EvalError(
                f"{ckpt}: trained on {len(seen)} of the {len(scored)} materials {ckpts[0]} "
                f"holds out (e.g. {seen[0]}): compare runs that hold out the same materials "
                "(--holdout-seed, --holdout-fraction), or --on a store none trained on"
            )
