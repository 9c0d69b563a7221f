"""Render-job results → shard payloads (what the farm hands to ``write_shard``)."""

from __future__ import annotations

import numpy as np

from render_jobs.results import MaterialRender
from storage.schema import Layout, encode_maps
from storage.writer import ShardPayload


def payload_from_renders(
    layout: Layout, shard: int, results: list[MaterialRender], records: list[dict]
) -> ShardPayload:
    """Pack one shard from its materials' results (in material order) and their records
    (``kind``, ``source_id``, ``spec``)."""
    materials = layout.shard_materials(shard)
    if len(results) != len(materials):
        raise ValueError(f"shard {shard} holds {len(materials)} materials, got {len(results)}")
    renders = [r for res in results for r in res.renders]
    return ShardPayload(
        maps=np.stack([encode_maps(res.maps.as_dict()) for res in results]),
        renders=np.stack([r.radiance for r in renders]).astype(np.float16),
        material_index=np.repeat(np.asarray(materials, np.int32), layout.suns_per_material),
        sun_direction=np.array([r.sun.direction for r in renders], np.float32),
        turbidity=np.array([r.sun.turbidity for r in renders], np.float32),
        seed=np.array([r.seed for r in renders], np.int64),
        render_seconds=np.array([r.seconds for r in renders], np.float32),
        materials=list(records),
    )
