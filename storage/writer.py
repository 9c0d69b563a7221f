"""Creating stores and writing shards: whole shards only, then an atomic commit record.

The protocol (DESIGN.md: zarr has no locks): every array is created once, full size, by
``create_store``; each shard is then written whole by exactly one writer (``write_shard``),
its files are made durable, and only then is ``commits/<shard>.json`` put atomically. A crash
before the put leaves the shard invisible (``pending``) and re-writable; writers of different
shards share no object, so any number of processes on any number of machines may write at once.
"""

from __future__ import annotations

import json
import os
import platform
import socket
import time
from dataclasses import dataclass, field

import numpy as np
from zarr.codecs import Crc32cCodec, ZstdCodec

from storage.backend import Backend
from storage.errors import ShardCommittedError, StoreError
from storage.reader import ShardStore, commit_key
from storage.schema import (
    ATTRS_KEY,
    KINDS,
    MAPS_CHANNELS,
    PER_SAMPLE,
    SCHEMA_VERSION,
    Layout,
)

ZSTD_LEVEL = 3


def _compressors():
    return [ZstdCodec(level=ZSTD_LEVEL), Crc32cCodec()]


def software_versions() -> dict[str, str]:
    import numcodecs
    import zarr

    return {
        "python": platform.python_version(),
        "numpy": np.__version__,
        "zarr": zarr.__version__,
        "numcodecs": numcodecs.__version__,
    }


def create_store(
    url: str,
    layout: Layout,
    settings: dict,
    storage_options: dict | None = None,
    exist_ok: bool = False,
) -> ShardStore:
    """Create an empty store for ``layout``; ``settings`` (render settings, camera, geometry
    hash, anything JSON) go into its attributes. With ``exist_ok``, an existing store with the
    same layout and settings is opened instead; a different one is refused, naming the field."""
    backend = Backend(url, storage_options)
    if backend.get("zarr.json") is not None:
        if not exist_ok:
            raise StoreError(f"{url}: a store already exists here")
        store = ShardStore(url, storage_options)
        store.check_compatible(layout, settings)
        return store
    group = backend.open_group(mode="w")
    group.attrs[ATTRS_KEY] = {
        "schema_version": SCHEMA_VERSION,
        "layout": layout.to_dict(),
        "settings": settings,
        "software": software_versions(),
        "created": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
    }
    r, m, n, s = layout.resolution, layout.num_materials, layout.num_samples, layout.shard_size
    mps = layout.materials_per_shard
    group.create_array(
        "maps",
        shape=(m, MAPS_CHANNELS, r, r),
        dtype="uint8",
        chunks=(1, MAPS_CHANNELS, r, r),
        shards=(mps, MAPS_CHANNELS, r, r),
        compressors=_compressors(),
        fill_value=0,
    )
    group.create_array(
        "renders",
        shape=(n, 3, r, r),
        dtype="float16",
        chunks=(1, 3, r, r),
        shards=(s, 3, r, r),
        compressors=_compressors(),
        fill_value=0,
    )
    for name, (tail, dtype) in PER_SAMPLE.items():
        group.create_array(
            name,
            shape=(n, *tail),
            dtype=dtype,
            chunks=(s, *tail),
            compressors=_compressors(),
            fill_value=0,
        )
    return ShardStore(url, storage_options)


@dataclass
class ShardPayload:
    """One shard's data, as ``write_shard`` takes it and ``ShardStore.read_shard`` returns it.

    ``maps`` ``(m, 11, H, W) uint8`` (``schema.encode_maps``); ``renders`` ``(n, 3, H, W)``
    float16 linear HDR; per sample: ``material_index (n,) int32``, ``sun_direction (n, 3)``,
    ``turbidity (n,)``, ``seed (n,) int64``, ``render_seconds (n,)``; ``materials``: one dict
    per material (``kind``, ``source_id``, ``spec``).
    """

    maps: np.ndarray
    renders: np.ndarray
    material_index: np.ndarray
    sun_direction: np.ndarray
    turbidity: np.ndarray
    seed: np.ndarray
    render_seconds: np.ndarray
    materials: list[dict] = field(default_factory=list)


def _check_payload(store: ShardStore, shard: int, p: ShardPayload) -> None:
    layout = store.layout
    samples, materials = layout.shard_samples(shard), layout.shard_materials(shard)
    n, m, r = len(samples), len(materials), layout.resolution
    expected = {
        "maps": ((m, MAPS_CHANNELS, r, r), np.uint8),
        "renders": ((n, 3, r, r), np.float16),
        "material_index": ((n,), np.int32),
        "sun_direction": ((n, 3), np.float32),
        "turbidity": ((n,), np.float32),
        "seed": ((n,), np.int64),
        "render_seconds": ((n,), np.float32),
    }
    for name, (shape, dtype) in expected.items():
        arr = getattr(p, name)
        if arr.shape != shape:
            raise StoreError(f"shard {shard}: {name} has shape {arr.shape}, expected {shape}")
        if arr.dtype != dtype:
            raise StoreError(f"shard {shard}: {name} is {arr.dtype}, expected {np.dtype(dtype)}")
    want = np.repeat(np.asarray(materials), layout.suns_per_material)
    if not np.array_equal(p.material_index, want):
        raise StoreError(f"shard {shard}: material_index does not match the layout")
    if len(p.materials) != m:
        raise StoreError(f"shard {shard}: {len(p.materials)} material records, expected {m}")
    for rec in p.materials:
        if rec.get("kind") not in KINDS or "source_id" not in rec:
            raise StoreError(f"shard {shard}: material record {rec!r} lacks kind/source_id")
    if not np.all(np.isfinite(p.renders)):
        raise StoreError(f"shard {shard}: renders hold NaN or Inf")


def write_shard(
    store: ShardStore, shard: int, payload: ShardPayload, overwrite: bool = False
) -> dict:
    """Write ``shard`` whole, make it durable, then commit it; returns the commit record."""
    _check_payload(store, shard, payload)
    backend = store.backend
    if store.commit_record(shard) is not None:
        if not overwrite:
            raise ShardCommittedError(
                f"{store.url}: shard {shard} is already committed (pass overwrite to replace it)"
            )
        backend.delete(commit_key(shard))  # invisible before its bytes change
        store._known.pop(shard, None)
        store._meta.pop(shard, None)
        store._maps_cache.clear()
    group = backend.open_group(mode="r+")
    samples, materials = store.layout.shard_samples(shard), store.layout.shard_materials(shard)
    group["maps"][materials.start : materials.stop] = payload.maps
    group["renders"][samples.start : samples.stop] = payload.renders
    for name in PER_SAMPLE:
        group[name][samples.start : samples.stop] = getattr(payload, name)
    keys = store.shard_keys(shard)
    backend.make_durable(keys)
    record = {
        "shard": shard,
        "samples": [samples.start, samples.stop],
        "materials": [
            {"index": i, **rec} for i, rec in zip(materials, payload.materials, strict=True)
        ],
        "files": {key: backend.size(key) for key in keys},
        "written_by": f"{socket.gethostname()}:{os.getpid()}",
        "committed": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
    }
    backend.put_atomic(commit_key(shard), json.dumps(record, indent=1).encode())
    return record
