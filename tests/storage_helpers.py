"""Synthetic shard payloads (fast) for storage tests; real renders come from conftest."""

from __future__ import annotations

import numpy as np

from storage.schema import Layout, ShardPayload


def synthetic_payload(layout: Layout, shard: int, seed: int = 0) -> ShardPayload:
    """Random maps and renders of ``shard``'s samples, drawn by ``seed``; material ``i`` is
    ``m{i}`` for seed 0 and ``s{seed}m{i}`` for the others (another material)."""
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
                "source_id": f"s{seed}m{i}" if seed else f"m{i}",
                "spec": {"seed": i},
            }
            for i in m
        ],
    )


def rendered_store(worker, path: str, sources: list[str], suns: int, shard_size: int):
    """A store of real renders by the session's Blender ``worker``, written shard by shard as
    the farm does, with its screen UV layout; returns ``(store, results)`` (results: one
    ``MaterialRender`` a material)."""
    from render_jobs.geometry import geometry_hash, shaderball
    from render_jobs.materials import load_maps, specs_from_sources
    from render_jobs.specs import derive_seed
    from render_jobs.sun import sample_suns
    from storage.convert import pack_material, payload_from_packed
    from storage.writer import create_store, put_screen_uv, write_shard

    specs = specs_from_sources(sources, dataset_seed=0)
    layout = Layout(len(specs), suns, worker.settings.resolution, shard_size)
    settings = {
        "render": worker.settings.to_dict(),
        "samples": worker.settings.samples,  # as farm stores record it
        "texture_tiling": worker.settings.texture_tiling,
        "geometry_hash": geometry_hash(shaderball()),
    }
    store = create_store(path, layout, settings)
    put_screen_uv(store, worker.screen_uv(4))
    results = []
    for i, spec in enumerate(specs):
        drawn = sample_suns(np.random.default_rng(derive_seed(0, i)), suns)
        seeds = [derive_seed(0, i, k) for k in range(suns)]
        results.append(worker.render_material(load_maps(spec), drawn, seeds))
    for shard in range(layout.num_shards):
        mats = layout.shard_materials(shard)
        records = [
            {"kind": specs[i].kind, "source_id": specs[i].source_id, "spec": specs[i].to_dict()}
            for i in mats
        ]
        packed = [pack_material(results[i]) for i in mats]
        payload = payload_from_packed(layout, shard, packed, records)
        write_shard(store, shard, payload)
    return store, results
