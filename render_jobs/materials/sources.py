"""Material source strings into specs, and specs into validated maps."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from render_jobs.errors import MaterialError
from render_jobs.materials.files import Reading, read_svbrdf, read_svbrdf_bytes, scan_svbrdf_dir
from render_jobs.materials.maps import MapBytes, MaterialMaps
from render_jobs.materials.procedural import DEFAULT_MAP_RESOLUTION, procedural_maps
from render_jobs.materials.uniform import sample_uniform, uniform_maps
from render_jobs.specs import MaterialSpec, UniformValues, derive_seed

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


ONE_HELP = (
    "uniform or procedural (random), uniform:seed=S or procedural:seed=S (as a store names "
    "its materials), uniform:diffuse=R,G,B;specular=R,G,B;roughness=X (sRGB values in [0, 1] "
    "or #rrggbb; normal_tilt=DEG;normal_azimuth=DEG optional), or a PATH (svbrdf:PATH): a "
    "5-panel PNG or a per-map folder"
)
_UNIFORM_KEYS = {
    "diffuse": "diffuse",
    "specular": "specular",
    "roughness": "roughness",
    "normal_tilt": "normal_tilt_deg",
    "normal_azimuth": "normal_azimuth_deg",
}


def one_material(
    text: str, seed: int = 0, map_resolution: int = DEFAULT_MAP_RESOLUTION
) -> MaterialSpec:
    """The one material that ``text`` names (forms: :data:`ONE_HELP`); bare ``uniform`` and
    ``procedural`` are drawn from ``seed``. Raises :class:`MaterialError` naming ``text``;
    reads no file (:func:`load_maps` validates)."""
    kind, sep, arg = text.partition(":")
    if kind in ("uniform", "procedural") and not sep:
        return make_spec(kind, derive_seed(seed, 0), map_resolution=map_resolution)
    if kind in ("uniform", "procedural") and arg.startswith("seed="):
        try:
            value = int(arg.removeprefix("seed="))
        except ValueError:
            raise MaterialError(f"{text}: the seed must be an integer") from None
        if value < 0:
            raise MaterialError(f"{text}: the seed must be >= 0")
        return make_spec(kind, value, map_resolution=map_resolution)
    if kind == "uniform" and sep:
        values = _uniform_values(text, arg)
        return MaterialSpec("uniform", text, uniform=values)
    if kind == "procedural" and sep:
        raise MaterialError(f"{text}: expected procedural:seed=S")
    path = Path(arg if kind == "svbrdf" and sep else text)
    if not path.exists():
        raise MaterialError(
            f"{text}: no such file or folder (a material is uniform, procedural, "
            "uniform:seed=S, procedural:seed=S, uniform:diffuse=...;specular=...;roughness=..., "
            "or a 5-panel PNG or per-map folder)"
        )
    return make_spec("svbrdf", 0, path)


def _uniform_values(text: str, arg: str) -> UniformValues:
    """``diffuse=...;specular=...;roughness=...`` → values (diffuse, specular, roughness
    required)."""
    fields: dict[str, object] = {}
    for part in filter(None, (p.strip() for p in arg.split(";"))):
        key, eq, value = part.partition("=")
        name = _UNIFORM_KEYS.get(key.strip())
        if not eq or name is None:
            raise MaterialError(
                f"{text}: {part!r} is not one of {', '.join(k + '=' for k in _UNIFORM_KEYS)}"
            )
        fields[name] = (
            _colour(text, key, value)
            if name in ("diffuse", "specular")
            else (_number(text, key, value))
        )
    missing = [k for k in ("diffuse", "specular", "roughness") if k not in fields]
    if missing:
        raise MaterialError(f"{text}: {missing[0]}= is missing")
    if not 0 <= float(fields["roughness"]) <= 1:  # type: ignore[arg-type]
        raise MaterialError(f"{text}: roughness must lie in [0, 1]")
    return UniformValues(**fields)  # type: ignore[arg-type]


def _number(text: str, key: str, value: str) -> float:
    try:
        return float(value)
    except ValueError:
        raise MaterialError(f"{text}: {key}={value!r} is not a number") from None


def _colour(text: str, key: str, value: str) -> tuple[float, float, float]:
    """``#rrggbb``, ``R,G,B`` or one grey value, sRGB in [0, 1]."""
    value = value.strip()
    if value.startswith("#") and len(value) == 7:
        try:
            rgb = tuple(int(value[i : i + 2], 16) / 255 for i in (1, 3, 5))
        except ValueError:
            raise MaterialError(f"{text}: {key}={value!r} is not a #rrggbb colour") from None
    else:
        parts = [_number(text, key, v) for v in value.split(",")]
        if len(parts) not in (1, 3):
            raise MaterialError(f"{text}: {key}= takes 1 or 3 values, not {len(parts)}")
        rgb = tuple(parts * 3 if len(parts) == 1 else parts)
    if not all(0 <= c <= 1 for c in rgb):
        raise MaterialError(f"{text}: {key}= values must lie in [0, 1]")
    return rgb  # type: ignore[return-value]


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


def load_map_bytes(spec: MaterialSpec) -> MapBytes:
    """``MapBytes.of(load_maps(spec))``, bit for bit: what a render worker sends Blender and the
    viewer maps. A file material is read straight to 8 bits (no float maps), so a render
    worker or the viewer holds a quarter of the bytes while it reads."""
    if spec.kind == "svbrdf" and spec.path is not None:
        return read_svbrdf_bytes(Path(spec.path))[0]
    return MapBytes.of(load_maps(spec))
