"""Synthetic shard payloads (fast) for storage tests; real renders come from conftest."""

from __future__ import annotations

import numpy as np

from storage.schema import Layout
from storage.writer import ShardPayload


def synthetic_payload(layout: Layout, shard: int, seed: int = 0) -> ShardPayload:
    rng = np.random.default_rng([seed, shard])
    s, m, r = layout.shard_samples(shard), layout.shard_materials(shard), layout.resolution
    z = rng.uniform(0.2, 1.0, len(s))
    phi = rng.uniform(0, 2 * np.pi, len(s))
    d = np.stack([np.sqrt(1 - z**2) * np.cos(phi), np.sqrt(1 - z**2) * np.sin(phi), z], 1)
    return ShardPayload(
        maps=rng.integers(0, 256, (len(m), 11, r, r), dtype=np.uint8),
        renders=rng.gamma(1.0, 0.3, (len(s), 3, r, r)).astype(np.float16),
        material_index=np.repeat(np.asarray(m, np.int32), layout.suns_per_material),
        sun_direction=d.astype(np.float32),
        turbidity=rng.uniform(2, 10, len(s)).astype(np.float32),
        seed=np.arange(s.start, s.stop, dtype=np.int64),
        render_seconds=rng.uniform(0.1, 1, len(s)).astype(np.float32),
        materials=[
            {
                "kind": "procedural" if i % 2 else "uniform",
                "source_id": f"m{i}",
                "spec": {"seed": i},
            }
            for i in m
        ],
    )
