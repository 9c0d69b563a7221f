"""Evaluation on held-out materials: PSNR, SSIM and FLIP, overall and per material kind.

All are computed in the tonemapped display space the model predicts (``[0, 1]``), over the
whole frame. SSIM: Gaussian window 11, σ 1.5, K1 0.01, K2 0.03, per channel, valid region
(Wang et al. 2004). The held-out materials are the ones the checkpoint's run never trained on:
its run's held-out split, or whole stores of other materials (``--on``). :class:`Tally` scores
any pairs of display images the same way (the quality comparison scores Cycles baselines
with it).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from shaderball.errors import UserError
from shaderball.progress import bar
from storage.backend import write_atomic
from storage.catalog import Catalog
from storage.errors import StoreError
from storage.reader import Store
from trainer.intervals import cluster_mean
from trainer.rendering.base import MapsRenderer
from trainer.rendering.load import load_renderer
from trainer.samples import SampleReader
from trainer.scoring import Tally, spread, write_grid


class EvalError(UserError, ValueError):
    """Nothing to evaluate, or stores that do not match the checkpoint."""


class NoCatalog(EvalError):
    """The model names no stores of its run (``trainer export --no-catalog``)."""


def test_split(
    renderer: MapsRenderer, stores: list[str] | None, on: list[str] | None, trained: bool = False
):
    """What a checkpoint is evaluated on: its run's held-out materials (in ``stores``, the
    run's stores at another address, when given), or every sample of the stores ``on``,
    which must not be stores the run trained on (unchecked for a model exported without
    its run's catalog: :func:`trained_on_is_checked`); with ``trained``, the run's training
    materials instead of its held-out ones (how well it fits what it saw)."""
    if renderer.catalog is None and stores:
        raise NoCatalog("--store: the model names no stores of its run (exported --no-catalog)")
    if renderer.catalog is None and not on:
        raise NoCatalog(
            "the model names no stores of its run (exported --no-catalog), so its held-out "
            "materials are unknown: evaluate it --on a store of other materials"
        )
    if on:
        trained = trained_sources(renderer, stores) if trained_on_is_checked(renderer) else set()
        for url in on:
            store = Store(url)
            if store.layout.resolution != renderer.config.resolution:
                raise EvalError(
                    f"{url}: {store.layout.resolution}², the network renders "
                    f"{renderer.config.resolution}²"
                )
            seen = sorted({m["source_id"] for m in store.materials().values()} & trained)
            if seen:
                raise EvalError(
                    f"{url}: {len(seen)} of its materials were trained on (e.g. {seen[0]}); "
                    "--on takes stores of other materials"
                )
        return Catalog.snapshot(list(on), 0, 0.0, None).split("all")
    catalog = _catalog(renderer, stores)
    _run_stores(catalog)  # one not where the run recorded it is named, with what to do
    if trained:
        return catalog.split("train")
    split = catalog.split("test")
    if len(split) == 0:
        raise EvalError(
            "no held-out samples: the run held out no materials (train with --holdout-fraction "
            "> 0, or evaluate --on a store of other materials)"
        )
    return split


def trained_on_is_checked(renderer: MapsRenderer) -> bool:
    """Whether ``--on`` stores are checked against the materials the run trained on: not
    for a model that names no stores of its run."""
    return renderer.catalog is not None


def _catalog(renderer: MapsRenderer, stores: list[str] | None) -> Catalog:
    """The run's catalog, its stores at ``stores`` when given."""
    catalog = Catalog.from_dict(renderer.catalog)
    if stores:
        if len(stores) != len(catalog.urls):
            raise EvalError(
                f"the checkpoint's run trained on {len(catalog.urls)} store(s) "
                f"({', '.join(catalog.urls)}), {len(stores)} given"
            )
        catalog.urls = list(stores)
    return catalog


def _run_stores(catalog: Catalog) -> list[Store]:
    """The stores the run trained on; an :class:`EvalError` that says how to point at one
    that is not where the run recorded it, or that is not the run's (another resolution,
    or without the shards the run read)."""
    out = []
    for url, shards in zip(catalog.urls, catalog.shards, strict=True):
        try:
            store = Store(url)
        except StoreError as exc:
            raise EvalError(
                f"{exc}: the run's store is not there; --store says where it is"
            ) from None
        if store.layout.resolution != catalog.resolution:
            raise EvalError(
                f"{url}: {store.layout.resolution}², the run's stores are "
                f"{catalog.resolution}²: not the run's store (--store names where it is)"
            )
        gone = sorted(set(shards) - set(store.committed_shards()))
        if gone:
            raise EvalError(
                f"{url}: {len(gone)} shard(s) the run read are not committed there (e.g. "
                f"shard {gone[0]}): not the run's store (--store names where it is)"
            )
        out.append(store)
    return out


def trained_sources(renderer: MapsRenderer, stores: list[str] | None) -> set[str]:
    """Source ids of the materials the run trained on, as its catalog names them, or read
    from its stores (at ``stores`` when given) for a catalog kept without them."""
    catalog = Catalog.from_dict(renderer.catalog)
    if catalog.records_sources:  # read no store, wherever they are
        return catalog.material_sources()[0]
    catalog = _catalog(renderer, stores)
    return catalog.material_sources(_run_stores(catalog))[0]


def evaluate(
    ckpt,
    stores: list[str] | None = None,
    batch_size: int = 8,
    grid: Path | None = None,
    grid_count: int = 4,
    device: str = "auto",
    on: list[str] | None = None,
    weights: str = "auto",
    per_sample: Path | None = None,
    trained: bool = False,
) -> dict:
    """Metrics of checkpoint ``ckpt`` (or a model ``trainer export`` wrote, run in ONNX
    Runtime: :func:`trainer.rendering.infer.load_renderer`) on its run's held-out split, or on every
    sample of the stores ``on`` (:func:`test_split`); writes a ground truth | prediction |
    error PNG grid of ``grid_count`` samples spread over them to ``grid`` when given, and each
    sample's scores to the CSV file ``per_sample`` (:func:`write_sample_table`). ``weights``:
    which of a checkpoint's (:func:`trainer.checkpoint.weights`); ``trained``: on the run's
    training materials instead (:func:`test_split`)."""
    renderer = load_renderer(ckpt, device, weights)
    try:
        split = test_split(renderer, stores, on, trained)
    except NoCatalog as exc:
        raise NoCatalog(f"{ckpt}: {exc}") from None
    scored = score([renderer], split, batch_size, grid_count)
    result = {
        "checkpoint_step": renderer.step,
        "runtime": renderer.runtime,
        "weights": renderer.weights,
        # whether the --on stores were checked to hold no material the run trained on
        "on_checked_against_run": trained_on_is_checked(renderer) if on else None,
        "samples": len(split),
        "on": list(on) if on else None,
        "split": "train" if trained else "test",
        **scored.summary(),
    }
    if grid is not None and scored.shown:
        write_grid(grid, scored.shown)
        result["grid"] = str(grid)
    if per_sample is not None:
        write_sample_table(per_sample, split, scored)
        result["per_sample"] = str(per_sample)
    return result


@dataclass
class Scored:
    """What :func:`score` measured: a :class:`Tally` per renderer (samples in the split's
    order), each sample's material as ``(store, material)`` and its kind, samples spread over
    the split (:func:`spread`) as ``(target, prediction of each renderer)`` display images for
    a grid, and the stores it read."""

    tallies: list[Tally]
    materials: list[tuple[int, int]]
    shown: list[tuple[np.ndarray, ...]]
    #: the split's stores as read (their per-shard metadata cached)
    stores: list[Store]
    kinds: list[str] = field(default_factory=list)

    def summary(self, which: int = 0) -> dict:
        """Renderer ``which``'s :meth:`Tally.summary`, each row (overall and per kind) with
        its count of materials and its PSNR's interval over them (``psnr_low``,
        ``psnr_high``: :func:`trainer.intervals.cluster_mean`, None under
        ``MIN_MATERIALS``)."""
        out = self.tallies[which].summary()
        psnr = np.array(self.tallies[which].scores["all"], np.float64).reshape(-1, 3)[:, 0]
        groups = np.array(self.materials, np.int64).reshape(-1, 2)
        kinds = np.array(self.kinds)

        out["overall"].update(_psnr_interval(psnr, groups))
        for kind, row in out["by_kind"].items():
            row.update(_psnr_interval(psnr[kinds == kind], groups[kinds == kind]))
        return out


def _psnr_interval(psnr: np.ndarray, groups: np.ndarray) -> dict:
    m = cluster_mean(psnr, groups)
    low, high = (None if v is None else round(v, 3) for v in (m["low"], m["high"]))
    return {"materials": m["materials"], "psnr_low": low, "psnr_high": high}


def score(renderers: list[MapsRenderer], split, batch_size: int, grid_count: int) -> Scored:
    """Every renderer on every sample of ``split``, each batch read once. The targets are
    the first renderer's tonemap of the renders (renderers compared must share it)."""
    reader = SampleReader(split)
    kinds = [{m: rec["kind"] for m, rec in s.materials().items()} for s in reader.stores]
    out = Scored([Tally() for _ in renderers], [], [], reader.stores, [])
    ids = np.arange(len(split))
    show = set(spread(len(split), grid_count).tolist())
    batches = range(0, len(ids), batch_size)
    for lo in bar(batches, desc="eval", unit="batch"):
        batch = reader.batch(ids[lo : lo + batch_size])
        mats = []
        for i in batch["id"].tolist():
            store, sample = split.refs[i]
            mats.append((int(store), reader.stores[store].layout.material_of_sample(int(sample))))
        names = [kinds[s][m] for s, m in mats]
        target = renderers[0].tonemap(batch["render"])
        preds = []
        for renderer, tally in zip(renderers, out.tallies, strict=True):
            pred = renderer.render_batch(batch["maps"], batch["light"])
            tally.add(pred, target.to(pred.device), names)
            preds.append(pred.cpu().numpy())
        out.materials += mats
        out.kinds += names
        for j, i in enumerate(batch["id"].tolist()):
            if i in show:
                out.shown.append((target[j].numpy(), *(p[j] for p in preds)))
    return out


#: the per-sample table's columns before the scores: where the sample is, its material, its sun
SAMPLE_COLUMNS = ("store", "sample", "material", "source", "kind", "sun_x", "sun_y", "sun_z",
                  "sun_elevation_deg", "turbidity")  # fmt: skip


def write_sample_table(path: Path, split, scored: Scored) -> None:
    """A CSV file of every sample :func:`score` scored, in its order: ``SAMPLE_COLUMNS``,
    then ``psnr_I``, ``ssim_I`` and ``flip_I`` of each renderer ``I`` (1 is the first);
    written whole or not at all."""
    import csv
    import io

    stores = scored.stores
    records = [store.materials() for store in stores]
    scores = [t.scores["all"] for t in scored.tallies]
    text = io.StringIO()
    out = csv.writer(text, lineterminator="\n")
    out.writerow([*SAMPLE_COLUMNS, *(f"{m}_{i}" for i in range(1, len(scores) + 1)
                                     for m in ("psnr", "ssim", "flip"))])  # fmt: skip
    for i, (s, k) in enumerate(split.refs.tolist()):
        material = stores[s].layout.material_of_sample(k)
        rec = records[s][material]
        sun, turbidity = stores[s].light(k)
        elevation = float(np.degrees(np.arcsin(np.clip(sun[2], -1, 1))))
        out.writerow([split.urls[s], k, material, rec["source_id"], rec["kind"],
                      *(f"{x:.5f}" for x in sun), f"{elevation:.2f}", f"{turbidity:g}",
                      *(f"{x:.5g}" for rows in scores for x in rows[i])])  # fmt: skip
    data = text.getvalue().encode()
    write_atomic(path, lambda f: f.write(data))
