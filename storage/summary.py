"""What ``shards ls`` and ``shards info`` report, as plain data (the CLI formats it)."""

from __future__ import annotations

import math
import os
from collections import Counter

import numpy as np

from render_jobs.screen_uv import FILE
from storage.errors import StoreError
from storage.reader import Store
from storage.schema import PACKED_CHANNELS, PER_SAMPLE


def list_shards(store: Store) -> list[dict]:
    commits = store.commits()
    rows = []
    for shard in range(store.layout.num_shards):
        rows.append(
            {
                "shard": shard,
                "samples": len(store.layout.shard_samples(shard)),
                "bytes": store.shard_bytes(shard),
                "state": store.shard_state(shard, commits),
            }
        )
    return rows


def disk_size(store: Store) -> int:
    b = store.backend
    if b.local:
        return sum(os.path.getsize(os.path.join(d, f)) for d, _, fs in os.walk(b.root) for f in fs)
    return int(b.fs.du(b.root))


def histogram(values: np.ndarray, lo: float, hi: float, bins: int) -> list[dict]:
    counts, edges = np.histogram(values, bins=bins, range=(lo, hi))
    return [
        {"from": float(a), "to": float(b), "count": int(c)}
        for a, b, c in zip(edges[:-1], edges[1:], counts, strict=True)
    ]


def store_info(store: Store) -> dict:
    lay, g = store.layout, store.group
    commits = store.commits()
    samples = [s for shard in sorted(commits) for s in lay.shard_samples(shard)]
    kinds = Counter(m["kind"] for rec in commits.values() for m in rec["materials"])
    stored = sum(store.shard_bytes(s) for s in commits)
    r = lay.resolution
    per_sample_raw = 3 * r * r * 2 + sum(
        math.prod(t) * np.dtype(d).itemsize for t, d in PER_SAMPLE.values()
    )
    raw = len(samples) * per_sample_raw + sum(kinds.values()) * PACKED_CHANNELS * r * r
    if samples:
        d = g["sun_direction"][:][samples]
        t = g["turbidity"][:][samples]
        elevation = np.degrees(np.arcsin(np.clip(d[:, 2], -1, 1)))
    else:
        elevation = t = np.zeros(0)
    return {
        "url": store.url,
        "schema_version": store.attrs["schema_version"],
        "layout": lay.to_dict(),
        "settings": store.settings,
        "software": store.attrs.get("software", {}),
        "created": store.attrs.get("created"),
        "shards": {"total": lay.num_shards, "committed": len(commits)},
        "samples": {"total": lay.num_samples, "committed": len(samples)},
        "materials_by_kind": dict(sorted(kinds.items())),
        "bytes": {
            "stored": stored,
            "raw": raw,
            "disk": disk_size(store),
            "compression_ratio": raw / stored if stored else None,
        },
        "screen_uv": screen_uv_info(store),
        "sun_elevation_deg": histogram(elevation, 0, 90, 9),
        "turbidity": histogram(t, 1, 10, 9),
    }


def screen_uv_info(store: Store) -> dict | None:
    """The screen UV layout's settings and size (``None``: the store has none; ``error``:
    it cannot be used)."""

    size = store.backend.size(FILE)
    if size is None:
        return None
    try:
        suv = store.screen_uv()
    except StoreError as exc:
        return {"bytes": size, "error": str(exc)}
    return {"bytes": size, **suv.meta()}


def text_histogram(rows: list[dict], width: int = 30, fmt: str = "{:>4.0f}-{:<4.0f}") -> str:
    peak = max((r["count"] for r in rows), default=0) or 1
    lines = []
    for r in rows:
        bar = "#" * round(width * r["count"] / peak)
        lines.append(f"  {fmt.format(r['from'], r['to'])} {bar:<{width}} {r['count']}")
    return "\n".join(lines)
