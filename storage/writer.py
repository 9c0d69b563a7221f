"""Creating stores and writing shards: whole shards only, then an atomic commit record.

The protocol (zarr has no locks: two writers of one shard would lose data): every array is
created once, full size, by ``create_store``; each shard is then written whole by exactly one
writer (``write_shard``), its files are made durable, and only then is
``commits/<shard>.json`` put atomically. A crash before the put leaves the shard invisible
(``pending``) and re-writable; writers of different shards share no object, so any number of
processes on any number of machines may write at once.
"""

from __future__ import annotations

import dataclasses
import json
import os
import platform
import socket
import time

import numpy as np
import zarr
from zarr.codecs import Crc32cCodec, ZstdCodec

from render_jobs.screen_uv import FILE, ScreenUVError
from storage.backend import Backend
from storage.errors import ShardCommittedError, StoreError
from storage.reader import Store
from storage.retry import retrying
from storage.schema import (
    ATTRS_KEY,
    FLOAT16_MANTISSA_BITS,
    KINDS,
    RENDER_BITS,
    SCHEMA_VERSION,
    Layout,
    ShardPayload,
    arrays,
    commit_key,
    round_renders,
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


@retrying  # every step rewrites the same metadata: a retry after a partial attempt is safe
def _create(group, layout: Layout, settings: dict) -> None:
    """The group's arrays, then its attributes, which make it a shard store."""
    for name, spec in arrays(layout).items():
        group.create_array(
            name,
            shape=spec.shape,
            dtype=spec.dtype,
            chunks=spec.chunks,
            shards=spec.shards,
            compressors=_compressors(),
            fill_value=0,
            overwrite=True,
        )
    group.attrs[ATTRS_KEY] = {
        "schema_version": SCHEMA_VERSION,
        "layout": layout.to_dict(),
        "settings": settings,
        "software": software_versions(),
        "created": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
    }


def create_store(
    url: str,
    layout: Layout,
    settings: dict,
    storage_options: dict | None = None,
    exist_ok: bool = False,
) -> Store:
    """Create an empty store for ``layout``; ``settings`` (render settings, camera, geometry
    hash, anything JSON) go into its attributes. With ``exist_ok``, an existing store with the
    same layout and settings is opened instead; a different one is refused, naming the field."""
    backend = Backend(url, storage_options)
    if backend.get("zarr.json") is not None:
        if not exist_ok:
            raise StoreError(f"{url}: a store already exists here")
        store = Store(url, storage_options)
        store.check_compatible(layout, settings)
        return store
    # mode "a" creates the group and never deletes what is there; its open retries itself
    _create(backend.open_group(mode="a"), layout, settings)
    return Store(url, storage_options)


def _check_payload(store: Store, shard: int, p: ShardPayload) -> None:
    layout = store.layout
    samples, materials = layout.shard_samples(shard), layout.shard_materials(shard)
    m = len(materials)
    for name, spec in arrays(layout).items():
        arr, dtype = getattr(p, name), np.dtype(spec.dtype)
        shape = spec.part(m if spec.per_material else len(samples))
        if arr.shape != shape:
            raise StoreError(f"shard {shard}: {name} has shape {arr.shape}, expected {shape}")
        if arr.dtype != dtype:
            raise StoreError(f"shard {shard}: {name} is {arr.dtype}, expected {dtype}")
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


@retrying  # rewriting a shard that is not committed yet is idempotent
def _write_arrays(group, layout: Layout, samples: range, materials: range, p: ShardPayload):
    # every chunk is written, even one equal to the fill value (zarr skips those by default):
    # a shard of material 0 alone has an all-zero material_index, and a missing file must
    # always mean lost data, never "zeros"
    with zarr.config.set({"array.write_empty_chunks": True}):
        for name, spec in arrays(layout).items():
            rows = materials if spec.per_material else samples
            group[name][rows.start : rows.stop] = getattr(p, name)


def write_shard(store: Store, shard: int, payload: ShardPayload, overwrite: bool = False) -> dict:
    """Write ``shard`` whole, make it durable, then commit it; returns the commit record.
    Its renders keep the mantissa bits the store's ``render_bits`` setting names (all where
    it has none), whoever writes it."""
    _check_payload(store, shard, payload)
    bits = store.settings.get(RENDER_BITS, FLOAT16_MANTISSA_BITS)
    payload = dataclasses.replace(payload, renders=round_renders(payload.renders, bits))
    backend = store.backend
    if store.commit_record(shard) is not None:
        if not overwrite:
            raise ShardCommittedError(
                f"{store.url}: shard {shard} is already committed (pass overwrite to replace it)"
            )
        backend.delete(commit_key(shard))  # invisible before its bytes change
        store.forget(shard)
    group = backend.open_group(mode="r+")
    samples, materials = store.layout.shard_samples(shard), store.layout.shard_materials(shard)
    _write_arrays(group, store.layout, samples, materials, payload)
    keys = store.shard_keys(shard)
    sizes = {key: backend.size(key) for key in keys}
    missing = [key for key, size in sizes.items() if size is None]
    if missing:
        raise StoreError(f"{store.url}: shard {shard}: {missing[0]} was not written")
    backend.make_durable(keys)
    record = {
        "shard": shard,
        "samples": [samples.start, samples.stop],
        "materials": [
            {"index": i, **rec} for i, rec in zip(materials, payload.materials, strict=True)
        ],
        "files": sizes,
        "written_by": f"{socket.gethostname()}:{os.getpid()}",
        "committed": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
    }
    backend.put_atomic(commit_key(shard), json.dumps(record, indent=1).encode())
    return record


def put_screen_uv(store: Store, screen_uv) -> None:
    """Keep ``screen_uv`` (:class:`render_jobs.screen_uv.ScreenUV`) with ``store``, in one
    atomic put (readers see the old layout or the whole new one); refused when it was made
    for another resolution or tiling."""

    try:
        screen_uv.check_fits({**store.settings, "resolution": store.layout.resolution}, store.url)
    except ScreenUVError as exc:
        raise StoreError(str(exc)) from None
    store.backend.put_atomic(FILE, screen_uv.to_bytes())
