"""Planning a job: materials x suns → shard-aligned render tasks, seeded (no Ray, no bpy).

A task is one material with all its suns (``render_jobs.specs.RenderJob``); the shards of the
store hold whole materials, so a shard is complete when its materials' tasks are. The same
sources, settings and seed always give the same tasks, suns and Cycles seeds.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, fields

import click

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
from storage.schema import FLOAT16_MANTISSA_BITS, RENDER_BITS, Layout, untrainable

#: materials a shard holds unless --shard-size says otherwise (25 samples at 5 suns)
MATERIALS_PER_SHARD = 5


def default_shard_size(suns: int) -> int:
    """Samples per shard when none is given: whole materials, so it always fits ``suns``."""
    return MATERIALS_PER_SHARD * suns


def _opt(default, help: str, flag: str | None = None, **extra):
    """A :class:`JobConfig` field that ``farm submit`` offers as an option (:func:`options`):
    its help, its flag (default: the field's name), and ``range`` (inclusive bounds, ``None``
    for none) that the dataclass checks and the option's type states."""
    return field(default=default, metadata={"help": help, "flag": flag, **extra})


@dataclass(frozen=True)
class JobConfig:
    """What defines a dataset (stored with it; a resubmit must match) plus how to run it.

    The one statement of ``farm submit``'s settings: its options are made from these fields
    (:func:`options`: flag, type, default, help), and the checks are here, so a job made in
    Python is refused as the command line refuses it, in one line naming the flag."""

    sources: tuple[str, ...] = _opt(
        (),
        "Material source (repeatable): N random uniform or procedural materials, or every "
        "SVBRDF in DIR.",
        flag="materials",
        short="-m",
        metavar="uniform:N|procedural:N|svbrdf:DIR",
    )
    out: str = _opt("", "Store to write (folder or s3:// URL).", short="-o")
    suns: int = _opt(DEFAULT_SUNS, "Random suns (direction + turbidity) per material.",
                     range=(1, 64))  # fmt: skip
    resolution: int = _opt(
        400,
        "Image side in pixels (farm submit: a multiple of 16, which the trainer needs).",
        range=(16, 8192),
    )
    samples: int = _opt(150, "Cycles samples per pixel.", range=(1, None))
    seed: int = _opt(0, "Seed: materials, suns and Cycles seeds follow from it.",
                     range=(0, None))  # fmt: skip
    shard_size: int | None = _opt(
        None,
        "Samples per shard, a multiple of --suns [default: 5 materials, 5 x --suns].",
        range=(1, None),
    )
    min_elevation_deg: float = DEFAULT_MIN_ELEVATION_DEG
    turbidity_range: tuple[float, float] = DEFAULT_TURBIDITY_RANGE
    map_resolution: int = DEFAULT_MAP_RESOLUTION
    texture_tiling: float = 2.0
    denoise: bool = _opt(
        False,
        "Denoise each render with Cycles' OpenImageDenoise (albedo + normal): a baseline "
        "store; with the same sources and --seed its samples pair with the ground truth's.",
    )  # never ground truth
    render_bits: int = _opt(
        FLOAT16_MANTISSA_BITS,
        "float16 mantissa bits kept in each stored render (10: all). Fewer compress better: "
        "at 6 (relative error at most 1/128) renders take about 0.6x the bytes and the rounding "
        "scores over 60 dB against the render, far above its Monte Carlo noise; for a "
        "store that must travel.",
        range=(1, FLOAT16_MANTISSA_BITS),
    )
    # one given sun for every material (direction x, y, z and turbidity), in place of random
    # ones: a fixed-light dataset for models without a light input; needs suns=1. Its option
    # is the direction (--fixed-sun X,Y,Z) and --fixed-turbidity, made in farm.cli
    fixed_sun: tuple[float, float, float, float] | None = None
    # how to run (not part of the dataset's identity)
    workers: int | None = _opt(
        None,
        "Blender workers, no more than the materials left; those Ray cannot place wait for "
        "room, and an autoscaling cluster adds nodes for them [default: what the cluster's "
        "free resources hold (CPUs / --cpus-per-worker, GPUs / --gpus-per-worker), growing "
        "as nodes join].",
        range=(1, None),
    )
    cpus_per_worker: int = _opt(1, "CPUs (and Cycles threads) per worker.", range=(1, None))
    gpus_per_worker: int = _opt(
        0, "1: each worker gets one GPU and renders with OptiX.", range=(0, 1)
    )
    address: str | None = _opt(
        None, "Ray cluster to join (else RAY_ADDRESS, else an embedded local Ray)."
    )
    ray_dashboard: bool = _opt(
        True, "Start the embedded Ray's dashboard (off saves CPU on small machines)."
    )
    max_attempts: int = _opt(
        3,
        "Tries per material (each retry on another worker where one can run it) before it is "
        "recorded as failed.",
        range=(1, None),
    )
    blocklist_after: int = 3
    task_timeout_s: float = _opt(
        600.0, "Seconds allowed per sun before the render counts as failed.",
        flag="task_timeout", range=(1, None),
    )  # fmt: skip
    backoff_s: float = 1.0
    retry_wait_s: float = _opt(
        120.0,
        "Seconds a retry waits for a starting worker that has not failed it (one started "
        "for it, or still waiting for room) before it runs on one that has; raise it for an "
        "autoscaler whose nodes take longer to start.",
        flag="retry_wait",
        range=(0, None),
    )
    recycle_after: int = _opt(
        500, "Restart a worker's Blender after this many renders.", range=(1, None)
    )
    rss_limit_mb: int = _opt(
        4096, "Restart a worker's Blender above this resident memory.", range=(64, None)
    )
    placement_timeout_s: float = _opt(
        300.0,
        "Seconds the job waits with no live worker (none placed yet, or every one gone) "
        "before it stops; raise it for an autoscaler that starts GPU nodes from zero.",
        flag="placement_timeout",
        range=(1, None),
    )

    def __post_init__(self) -> None:
        object.__setattr__(self, "sources", tuple(self.sources))
        if not self.sources:
            raise ValueError("--materials: give at least one material source")
        if not self.out:
            raise ValueError("--out: give the store to write")
        for f in fields(self):
            bounds, value = f.metadata.get("range"), getattr(self, f.name)
            if bounds is None or value is None:
                continue
            low, high = bounds
            if value < low or (high is not None and value > high):
                rule = f"at least {low}" if high is None else f"in [{low}, {high}]"
                raise ValueError(f"{flag_of(f)} must be {rule}, not {value!r}")
        if self.shard_size is None:
            object.__setattr__(self, "shard_size", default_shard_size(self.suns))
        elif self.shard_size % self.suns:
            raise ValueError(
                f"--shard-size {self.shard_size} must be a multiple of --suns {self.suns}"
            )
        if why := untrainable(self.resolution):
            raise ValueError(f"--{why}")
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
            # only where bits are dropped: a store made before the setting existed stays
            # the same dataset as one made with all 10
            **({RENDER_BITS: self.render_bits} if self.render_bits < FLOAT16_MANTISSA_BITS else {}),
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


def flag_of(f) -> str:
    """The option of a :class:`JobConfig` field, ``--like-this``."""
    return "--" + (f.metadata.get("flag") or f.name).replace("_", "-")


#: the fields of the options every command that renders offers (``farm preview`` too)
RENDER_OPTIONS = ("suns", "resolution", "samples", "seed")


def options(command, names: tuple[str, ...] | None = None):
    """Decorate a click command with an option for each :class:`JobConfig` field that has
    one (only ``names``, when given), its parameter named as the field."""
    chosen = [f for f in fields(JobConfig) if "help" in f.metadata]
    if names is not None:
        chosen = [f for f in chosen if f.name in names]
    for f in reversed(chosen):
        meta, flag = f.metadata, flag_of(f)
        decls = [flag, *([meta["short"]] if "short" in meta else []), f.name]
        kind = {"int": int, "float": float}.get(f.type.removesuffix(" | None"))
        if (bounds := meta.get("range")) is not None:
            low, high = bounds
            kind = (click.IntRange if kind is int else click.FloatRange)(low, high)
        extra = {"type": kind} if kind is not None else {}
        if f.type == "bool" and f.default:
            decls[0] = f"{flag}/--no-{flag[2:]}"
            extra = {"default": True, "show_default": True}
        elif f.type == "bool":
            extra = {"is_flag": True, "default": False}
        elif f.name == "sources":
            extra |= {"multiple": True, "required": True}
        elif f.name == "out":
            extra |= {"required": True}
        else:
            extra |= {"default": f.default, "show_default": f.default is not None}
        command = click.option(*decls, help=meta["help"], metavar=meta.get("metavar"),
                               **extra)(command)  # fmt: skip
    return command
