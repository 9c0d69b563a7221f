"""The small 400² store the training and inference benchmarks read, made by the real farm.

``out/bench-400.zarr``: 4 uniform + 4 procedural materials x 5 suns at 400², 4 spp (the
benchmarks time the network and the loader, not the renders' noise). Made once, then reused;
copy it to a GPU machine to benchmark there (``--store``), and there :func:`replicate` it into a
store long enough for GPU-speed epochs (its real renders repeated, materials renumbered).
"""

from __future__ import annotations

import dataclasses
from pathlib import Path

from farm.driver import submit
from farm.plan import JobConfig
from storage.reader import Store
from storage.schema import Layout
from storage.writer import create_store, write_shard

DEFAULT = "out/bench-400.zarr"


def ensure_store(path: str = DEFAULT) -> str:
    """``path`` if it holds a store, else a fresh one rendered there by ``farm submit``."""
    if (Path(path) / "zarr.json").exists():
        return path

    print(f"rendering the benchmark store {path} (40 frames at 400², 4 spp; once)", flush=True)
    cfg = JobConfig(
        sources=("uniform:4", "procedural:4"), out=path, resolution=400, samples=4, shard_size=10
    )
    summary = submit(cfg, progress=False, echo=lambda *_: None)
    if not summary.ok:
        raise RuntimeError(f"benchmark store failed: {summary.failed_materials}")
    return path


def replicate(src: str, dst: str, copies: int) -> str:
    """Write ``dst``: ``copies`` x every shard of ``src`` (all committed, whole shards), with
    material indices renumbered; returns ``dst``. For load tests where Blender is absent."""

    source = Store(src)
    lay = source.layout
    if source.committed_shards() != list(range(lay.num_shards)) or (
        lay.num_materials % lay.materials_per_shard
    ):
        raise ValueError(f"{src}: replicate needs a complete store of whole shards")
    layout = Layout(
        lay.num_materials * copies, lay.suns_per_material, lay.resolution, lay.shard_size
    )
    settings = {**source.settings, "replicated_from": str(src), "copies": copies}
    store = create_store(dst, layout, settings)
    for c in range(copies):
        for shard in range(lay.num_shards):
            p = source.read_shard(shard)
            p = dataclasses.replace(p, material_index=p.material_index + c * lay.num_materials)
            write_shard(store, c * lay.num_shards + shard, p)
    return dst
