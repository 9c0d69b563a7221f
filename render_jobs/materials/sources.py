"""Material source strings into specs, and specs into validated maps."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from render_jobs.errors import MaterialError
from render_jobs.materials.files import Reading, read_svbrdf, scan_svbrdf_dir
from render_jobs.materials.maps import MaterialMaps
from render_jobs.materials.procedural import DEFAULT_MAP_RESOLUTION, procedural_maps
from render_jobs.materials.uniform import sample_uniform, uniform_maps
from render_jobs.specs import MaterialSpec, derive_seed

SOURCE_HELP = "uniform:N, procedural:N or svbrdf:DIR"


def parse_source(text: str) -> tuple[str, int | Path]:
    """``"uniform:N"`` → ("uniform", N); ``"svbrdf:DIR"`` → ("svbrdf", Path(DIR))."""
    kind, sep, arg = text.partition(":")
    if not sep or not arg:
        raise MaterialError(f"material source {text!r}: expected {SOURCE_HELP}")
    if kind in ("uniform", "procedural"):
        try:
            count = int(arg)
        except ValueError:
            raise MaterialError(f"material source {text!r}: N must be an integer") from None
        if count < 1:
            raise MaterialError(f"material source {text!r}: N must be >= 1")
        return kind, count
    if kind == "svbrdf":
        return kind, Path(arg)
    raise MaterialError(f"material source {text!r}: unknown kind {kind!r} ({SOURCE_HELP})")


def make_spec(
    kind: str,
    seed: int,
    path: Path | None = None,
    map_resolution: int = DEFAULT_MAP_RESOLUTION,
) -> MaterialSpec:
    """One material spec; ``seed`` fixes uniform values and procedural patterns."""
    if kind == "uniform":
        values = sample_uniform(np.random.default_rng(seed))
        return MaterialSpec(kind, f"uniform:seed={seed}", seed=seed, uniform=values)
    if kind == "procedural":
        return MaterialSpec(
            kind, f"procedural:seed={seed}", seed=seed, map_resolution=map_resolution
        )
    if kind == "svbrdf":
        assert path is not None
        return MaterialSpec(kind, path.name, path=str(path))
    raise MaterialError(f"unknown material kind {kind!r}")


def specs_from_sources(
    sources: list[str], dataset_seed: int, map_resolution: int = DEFAULT_MAP_RESOLUTION
) -> list[MaterialSpec]:
    """Every material of every source, in order; material i is seeded by (dataset_seed, i)."""
    specs: list[MaterialSpec] = []
    for text in sources:
        kind, arg = parse_source(text)
        if kind == "svbrdf":
            assert isinstance(arg, Path)
            for path in scan_svbrdf_dir(arg):
                specs.append(make_spec("svbrdf", 0, path))
        else:
            assert isinstance(arg, int)
            for _ in range(arg):
                seed = derive_seed(dataset_seed, len(specs))
                specs.append(make_spec(kind, seed, map_resolution=map_resolution))
    return specs


def load_maps(spec: MaterialSpec) -> MaterialMaps:
    """The validated maps of ``spec`` (raises :class:`MaterialError` naming the culprit)."""
    return read_material(spec)[0]


def read_material(spec: MaterialSpec) -> tuple[MaterialMaps, Reading]:
    """The validated maps of ``spec`` and how they were read (files, workflow, conversions,
    files ignored); raises :class:`MaterialError` naming the culprit."""
    if spec.kind == "uniform":
        if spec.uniform is None:
            raise MaterialError(f"{spec.source_id}: uniform material has no values")
        return uniform_maps(spec.uniform, spec.source_id), Reading(spec.source_id, "uniform")
    if spec.kind == "procedural":
        if spec.seed is None:
            raise MaterialError(f"{spec.source_id}: procedural material has no seed")
        maps = procedural_maps(spec.seed, spec.map_resolution)
        return maps, Reading(spec.source_id, "procedural")
    if spec.path is None:
        raise MaterialError(f"{spec.source_id}: svbrdf material has no path")
    return read_svbrdf(Path(spec.path))
