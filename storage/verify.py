"""``shards verify``: every check a store's data can fail, shard by shard."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from storage.errors import StoreError
from storage.reader import Store
from storage.schema import arrays


@dataclass
class Report:
    checked: int = 0
    empty: int = 0
    problems: dict[int, list[str]] = field(default_factory=dict)  # shard -> reasons
    store_problems: list[str] = field(default_factory=list)

    @property
    def ok(self) -> bool:
        return not self.problems and not self.store_problems

    def add(self, shard: int, reason: str) -> None:
        self.problems.setdefault(shard, []).append(reason)


def _check_arrays(store: Store, report: Report) -> None:
    for name, spec in arrays(store.layout).items():
        try:
            actual = store.array(name)
        except KeyError:
            report.store_problems.append(f"array {name} is missing")
            continue
        if tuple(actual.shape) != spec.shape:
            report.store_problems.append(
                f"array {name} has shape {actual.shape}, expected {spec.shape}"
            )
        elif actual.dtype != np.dtype(spec.dtype):
            report.store_problems.append(f"array {name} is {actual.dtype}, expected {spec.dtype}")


def _check_shard(store: Store, shard: int, rec: dict, report: Report) -> None:
    lay = store.layout
    samples = lay.shard_samples(shard)
    if rec.get("shard") != shard or rec.get("samples") != [samples.start, samples.stop]:
        report.add(shard, "commit record does not match the layout's sample range")
    for key, size in rec.get("files", {}).items():
        actual = store.backend.size(key)
        if size is None and actual is None:
            continue  # recorded absent at commit (zarr skipped an all-fill chunk): reads as written
        if actual is None:
            report.add(shard, f"{key} is missing")
        elif actual != size:
            report.add(shard, f"{key} is {actual} bytes, its commit record says {size}")
    try:
        p = store.read_shard(shard)
    except Exception as exc:  # noqa: BLE001 - any decode failure is a finding, not a crash
        report.add(shard, f"unreadable: {type(exc).__name__}: {exc}")
        return
    renders = p.renders.astype(np.float32)
    if not np.all(np.isfinite(renders)):
        report.add(shard, f"renders hold {int((~np.isfinite(renders)).sum())} NaN/Inf values")
    elif renders.min() < 0:
        report.add(shard, f"renders hold negative radiance (min {renders.min():.3g})")
    want = np.repeat(np.asarray(lay.shard_materials(shard)), lay.suns_per_material)
    if not np.array_equal(p.material_index, want):
        report.add(shard, "material_index does not match the layout")
    d = p.sun_direction
    if not np.all(np.isfinite(d)) or np.abs(np.linalg.norm(d, axis=1) - 1).max() > 1e-3:
        report.add(shard, "sun_direction holds non-unit vectors")
    elif d[:, 2].min() <= 0:
        report.add(shard, "sun_direction holds suns below the horizon")
    t = p.turbidity
    if not np.all(np.isfinite(t)) or t.min() < 1 or t.max() > 10:
        report.add(shard, f"turbidity outside [1, 10] ([{t.min():.3g}, {t.max():.3g}])")
    if p.seed.min() < 0:
        report.add(shard, "negative seeds")
    rs = p.render_seconds
    if not np.all(np.isfinite(rs)) or rs.min() < 0:
        report.add(shard, "render_seconds holds negative or non-finite values")
    if len(rec.get("materials", [])) != len(lay.shard_materials(shard)):
        report.add(shard, "commit record lists the wrong number of materials")


def _check_screen_uv(store: Store, report: Report) -> None:
    """The screen UV layout, when the store has one: readable (zip CRCs) and fitting."""
    try:
        store.screen_uv()
    except StoreError as exc:
        report.store_problems.append(str(exc))


def verify(store: Store, progress=None) -> Report:
    """Check ``store``; ``progress(shard)`` is called after each shard."""
    report = Report()
    _check_arrays(store, report)
    _check_screen_uv(store, report)
    if report.store_problems:
        return report
    commits = store.commits()
    for shard in sorted(set(commits) - set(range(store.layout.num_shards))):
        report.add(shard, "commit record for a shard outside the layout")
    for shard in range(store.layout.num_shards):
        if shard in commits:
            report.checked += 1
            _check_shard(store, shard, commits[shard], report)
        elif store.shard_state(shard, commits) == "pending":
            report.add(shard, "data without a commit record (an interrupted write?)")
        else:
            report.empty += 1
        if progress is not None:
            progress(shard)
    return report
