"""Render-job results → shard payloads: the one place that packs what ``write_shard`` takes."""

from __future__ import annotations

import numpy as np

from render_jobs.results import MaterialRender
from storage.schema import Layout, ShardPayload, encode_maps


def pack_material(result: MaterialRender) -> dict:
    """One material's result in store form: ``maps (11, H, W) uint8``, ``renders (K, 3, H, W)
    float16``, ``sun_direction (K, 3)``, ``turbidity (K,)``, ``seed (K,)``, ``seconds (K,)``."""
    return {
        "maps": encode_maps(result.maps.as_dict()),
        "renders": np.stack([r.radiance for r in result.renders]).astype(np.float16),
        "sun_direction": np.array([r.sun.direction for r in result.renders], np.float32),
        "turbidity": np.array([r.sun.turbidity for r in result.renders], np.float32),
        "seed": np.array([r.seed for r in result.renders], np.int64),
        "seconds": np.array([r.seconds for r in result.renders], np.float32),
    }


def payload_from_packed(
    layout: Layout, shard: int, packed: list[dict], records: list[dict]
) -> ShardPayload:
    """Pack one shard from its materials' ``pack_material`` dicts (in material order) and
    their records (``kind``, ``source_id``, ``spec``)."""
    materials = layout.shard_materials(shard)
    if len(packed) != len(materials):
        raise ValueError(f"shard {shard} holds {len(materials)} materials, got {len(packed)}")
    return ShardPayload(
        maps=np.stack([p["maps"] for p in packed]),
        renders=np.concatenate([p["renders"] for p in packed]),
        material_index=np.repeat(np.asarray(materials, np.int32), layout.suns_per_material),
        sun_direction=np.concatenate([p["sun_direction"] for p in packed]),
        turbidity=np.concatenate([p["turbidity"] for p in packed]),
        seed=np.concatenate([p["seed"] for p in packed]),
        render_seconds=np.concatenate([p["seconds"] for p in packed]),
        materials=list(records),
    )
