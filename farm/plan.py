"""Planning a job: materials x suns → shard-aligned render tasks, seeded (no Ray, no bpy).

A task is one material with all its suns (``render_jobs.specs.RenderJob``); the shards of the
store hold whole materials, so a shard is complete when its materials' tasks are. The same
sources, settings and seed always give the same tasks, suns and Cycles seeds.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from render_jobs.geometry import geometry_hash, shaderball
from render_jobs.materials import specs_from_sources
from render_jobs.materials.procedural import DEFAULT_MAP_RESOLUTION
from render_jobs.specs import CAMERA, MaterialSpec, RenderJob, Sun, derive_seed
from render_jobs.sun import (
    DEFAULT_MIN_ELEVATION_DEG,
    DEFAULT_SUNS,
    DEFAULT_TURBIDITY_RANGE,
    suns_for_material,
)
from storage.schema import Layout

#: materials a shard holds unless --shard-size says otherwise (25 samples at 5 suns)
MATERIALS_PER_SHARD = 5


def default_shard_size(suns: int) -> int:
    """Samples per shard when none is given: whole materials, so it always fits ``suns``."""
    return MATERIALS_PER_SHARD * suns


@dataclass(frozen=True)
class JobConfig:
    """What defines a dataset (stored with it; a resubmit must match) plus how to run it."""

    sources: tuple[str, ...]
    out: str
    suns: int = DEFAULT_SUNS
    resolution: int = 400
    samples: int = 150
    seed: int = 0
    shard_size: int | None = None  # None: default_shard_size(suns)
    min_elevation_deg: float = DEFAULT_MIN_ELEVATION_DEG
    turbidity_range: tuple[float, float] = DEFAULT_TURBIDITY_RANGE
    map_resolution: int = DEFAULT_MAP_RESOLUTION
    texture_tiling: float = 2.0
    denoise: bool = False  # OIDN on each render: a baseline store, never ground truth
    # one given sun for every material (direction x, y, z and turbidity), in place of random
    # ones: a fixed-light dataset for models without a light input; needs suns=1
    fixed_sun: tuple[float, float, float, float] | None = None
    # how to run (not part of the dataset's identity)
    workers: int | None = None
    cpus_per_worker: int = 1
    gpus_per_worker: int = 0
    address: str | None = None
    ray_dashboard: bool = True  # the embedded Ray's dashboard (it costs CPU on small machines)
    max_attempts: int = 3
    blocklist_after: int = 3
    task_timeout_s: float = 600.0
    backoff_s: float = 1.0
    recycle_after: int = 500
    rss_limit_mb: int = 4096
    placement_timeout_s: float = 300.0

    def __post_init__(self) -> None:
        if self.shard_size is None:
            object.__setattr__(self, "shard_size", default_shard_size(self.suns))
        if self.fixed_sun is not None:
            if self.suns != 1:
                raise ValueError(f"--fixed-sun needs --suns 1, not {self.suns}")
            self.sun_for_all()  # checks it

    def sun_for_all(self) -> Sun:
        """The fixed sun (raises ``ValueError`` naming what is wrong with it)."""
        x, y, z, turbidity = self.fixed_sun
        norm = math.sqrt(x * x + y * y + z * z)
        if not norm > 0:
            raise ValueError("--sun must be a non-zero direction X,Y,Z")
        return Sun(direction=(x / norm, y / norm, z / norm), turbidity=turbidity)

    def dataset_settings(self) -> dict:
        """The settings that define the dataset: stored in the store, checked on resubmit."""
        return {
            "sources": list(self.sources),
            "suns": self.suns,
            "resolution": self.resolution,
            "samples": self.samples,
            "seed": self.seed,
            "min_elevation_deg": self.min_elevation_deg,
            "turbidity_range": list(self.turbidity_range),
            "map_resolution": self.map_resolution,
            "texture_tiling": self.texture_tiling,
            "camera": CAMERA.to_dict(),
            "geometry_hash": geometry_hash(shaderball()),
            "sky": "HOSEK_WILKIE",
            "denoising": self.denoise,
            "fixed_sun": list(self.fixed_sun) if self.fixed_sun else None,
        }


def material_specs(cfg: JobConfig) -> list[MaterialSpec]:
    return specs_from_sources(list(cfg.sources), cfg.seed, cfg.map_resolution)


def layout_for(cfg: JobConfig, num_materials: int) -> Layout:
    return Layout(num_materials, cfg.suns, cfg.resolution, cfg.shard_size)


def task_for(cfg: JobConfig, index: int, spec: MaterialSpec) -> RenderJob:
    """Material ``index`` with its suns and per-sun Cycles seeds."""
    if cfg.fixed_sun is not None:
        suns = [cfg.sun_for_all()]
    else:
        suns = suns_for_material(
            cfg.seed, index, cfg.suns, cfg.min_elevation_deg, tuple(cfg.turbidity_range)
        )
    seeds = tuple(derive_seed(cfg.seed, index, k) for k in range(cfg.suns))
    return RenderJob(material_index=index, material=spec, suns=tuple(suns), seeds=seeds)
