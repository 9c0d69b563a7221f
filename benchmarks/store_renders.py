"""A store's samples rendered again by Blender: the same materials, suns and scene settings
(resolution, texture tiling) at another number of samples per pixel, with denoising, or with
the Cycles seeds moved. The truth-noise table and the quality report's reference and Cycles
times take their renders from here, so they render the store's scene and nothing else."""

from __future__ import annotations

from collections import defaultdict

import numpy as np
from tqdm import tqdm

from render_jobs.materials import load_maps
from render_jobs.process import RenderProcess
from render_jobs.specs import MaterialSpec, RenderSettings
from storage.reader import Store


def store_settings(store: Store, spp: int, **more) -> RenderSettings:
    """The store's render settings at ``spp`` samples per pixel (``more``: e.g. ``denoise``)."""
    tiling = store.settings.get("texture_tiling", 2.0)
    return RenderSettings(
        resolution=store.layout.resolution, samples=spp, texture_tiling=tiling, **more
    )


def frames(store: Store, samples: list[int], seed_offset: int = 0) -> list[tuple]:
    """``(maps, sun, seed)`` of each sample, its Cycles seed moved by ``seed_offset`` (0: the
    store's own, which renders the store's image again); each material's maps loaded once."""
    specs, maps, out = store.materials(), {}, []
    for i in samples:
        sample = store.sample(i)
        m = sample.material_index
        if m not in maps:
            maps[m] = load_maps(MaterialSpec.from_dict(specs[m]["spec"]))
        out.append((maps[m], sample.sun, (sample.seed + seed_offset) % 2**31))
    return out


def render_again(
    store: Store, samples: list[int], spp: int, seed_offset: int = 0, each_alone: bool = False
) -> tuple[np.ndarray, np.ndarray]:
    """``(N, 3, R, R)`` float32 radiance of ``samples`` at ``spp`` and each one's seconds (its
    sun's render: scene changes, path tracing, EXR out and in; not the texture upload).

    By default each material's samples share one render call (its textures uploaded once);
    ``each_alone`` gives every sample a call of its own."""
    todo = frames(store, samples, seed_offset)
    calls = defaultdict(list)
    for k, i in enumerate(samples):
        calls[k if each_alone else store.layout.material_of_sample(i)].append(k)
    radiance, seconds = [None] * len(samples), np.zeros(len(samples))
    with RenderProcess(store_settings(store, spp)) as worker:
        for ks in tqdm(calls.values(), desc="render again", unit="call"):
            suns, seeds = [todo[k][1] for k in ks], [todo[k][2] for k in ks]
            result = worker.render_material(todo[ks[0]][0], suns, seeds)
            for k, r in zip(ks, result.renders, strict=True):
                radiance[k], seconds[k] = r.radiance, r.seconds
    return np.stack(radiance).astype(np.float32), seconds
