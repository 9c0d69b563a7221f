"""Plain, frozen, serialisable descriptions of a render (no ``bpy``).

A render is fully described by a :class:`MaterialSpec`, a :class:`Sun`, the job-wide
:class:`RenderSettings` and the fixed :data:`CAMERA`; the Blender backend turns them into a
scene. Every spec round-trips through ``to_dict``/``from_dict`` (JSON-safe), so it can travel
in farm tasks and shard metadata.

Coordinates: right-handed, metres, +Z up. The shaderball sits at the origin; the camera looks
at it from -Y. A sun direction is the unit vector from the scene *towards* the sun.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np

MATERIAL_KINDS = ("uniform", "procedural", "svbrdf")
DEVICES = ("CPU", "CUDA", "OPTIX")


class _Serialisable:
    def to_dict(self) -> dict[str, Any]:
        return dataclasses.asdict(self)  # type: ignore[call-overload]

    @classmethod
    def from_dict(cls, data: dict[str, Any]):
        names = {f.name for f in dataclasses.fields(cls)}  # type: ignore[arg-type]
        unknown = set(data) - names
        if unknown:
            raise ValueError(f"{cls.__name__}: unknown field(s) {sorted(unknown)}")
        values = {k: tuple(v) if isinstance(v, list) else v for k, v in data.items()}
        return cls(**values)


@dataclass(frozen=True)
class UniformValues(_Serialisable):
    """A spatially constant Cook-Torrance material.

    ``diffuse``/``specular`` are sRGB-encoded colours in [0, 1] (as a PNG map would hold them);
    ``roughness`` is Blender's GGX roughness r in [0, 1] (alpha = r**2); the normal is the
    unit tangent-space normal tilted by ``normal_tilt_deg`` from +Z towards azimuth
    ``normal_azimuth_deg``.
    """

    diffuse: tuple[float, float, float]
    specular: tuple[float, float, float]
    roughness: float
    normal_tilt_deg: float = 0.0
    normal_azimuth_deg: float = 0.0


@dataclass(frozen=True)
class MaterialSpec(_Serialisable):
    """Where a material's four maps come from.

    - ``uniform``: ``uniform`` holds the values;
    - ``procedural``: the generator runs from ``seed`` at ``map_resolution``;
    - ``svbrdf``: ``path`` is a 5-panel PNG (Deschaintre et al. 2018) or a folder of
      per-map files.

    ``source_id`` is a short, stable, human-readable id (generator + seed, or file name).
    """

    kind: str
    source_id: str
    seed: int | None = None
    path: str | None = None
    uniform: UniformValues | None = None
    map_resolution: int = 256

    def __post_init__(self) -> None:
        if self.kind not in MATERIAL_KINDS:
            raise ValueError(f"material kind must be one of {MATERIAL_KINDS}, got {self.kind!r}")

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> MaterialSpec:
        data = dict(data)
        if data.get("uniform") is not None:
            data["uniform"] = UniformValues.from_dict(data["uniform"])
        return cls(**data)


@dataclass(frozen=True)
class Sun(_Serialisable):
    """Sun direction (unit, towards the sun, z > 0) and Hosek-Wilkie turbidity in [1, 10]."""

    direction: tuple[float, float, float]
    turbidity: float

    def __post_init__(self) -> None:
        d = np.asarray(self.direction, dtype=np.float64)
        if d.shape != (3,) or not np.all(np.isfinite(d)) or abs(np.linalg.norm(d) - 1) > 1e-4:
            raise ValueError(f"sun direction must be a finite unit 3-vector, got {self.direction}")
        if d[2] <= 0:
            shown = ", ".join(f"{x:.3f}" for x in d)
            raise ValueError(f"sun must be above the horizon (z > 0), got ({shown})")
        if not 1.0 <= self.turbidity <= 10.0:
            raise ValueError(f"turbidity must lie in [1, 10], got {self.turbidity}")

    @property
    def elevation_deg(self) -> float:
        return math.degrees(math.asin(self.direction[2]))

    @property
    def azimuth_deg(self) -> float:
        """Angle from +X towards +Y, in [0, 360)."""
        return math.degrees(math.atan2(self.direction[1], self.direction[0])) % 360.0

    def label(self) -> str:
        return f"el {self.elevation_deg:.0f}° az {self.azimuth_deg:.0f}° T {self.turbidity:.1f}"


@dataclass(frozen=True)
class Camera(_Serialisable):
    """The fixed pinhole camera that frames the shaderball."""

    location: tuple[float, float, float] = (0.0, -4.6, 1.25)
    look_at: tuple[float, float, float] = (0.0, 0.0, -0.3)
    lens_mm: float = 50.0
    sensor_mm: float = 36.0


CAMERA = Camera()


@dataclass(frozen=True)
class RenderSettings(_Serialisable):
    """Job-wide Cycles settings.

    ``resolution``: square image side in pixels (paper: 400). ``samples``: paths per pixel
    (paper: 150), fixed (no adaptive sampling). ``denoise``: Cycles' OpenImageDenoise on the
    final image, guided by albedo and normal passes (a baseline's setting; ground truth is
    never denoised). ``device``: CPU, CUDA or OPTIX
    (GPU devices need a CUDA build of Blender's kernels and a GPU; each farm worker gets one).
    ``threads``: Cycles CPU threads, 0 = all cores. ``texture_tiling``: map repeats from pole to
    pole (twice as many around the equator, so texels stay square).
    """

    resolution: int = 400
    samples: int = 150
    device: str = "CPU"
    threads: int = 0
    texture_tiling: float = 2.0
    denoise: bool = False

    def __post_init__(self) -> None:
        if not 8 <= self.resolution <= 8192:
            raise ValueError(f"resolution must lie in [8, 8192], got {self.resolution}")
        if self.samples < 1:
            raise ValueError(f"samples must be >= 1, got {self.samples}")
        if self.device not in DEVICES:
            raise ValueError(f"device must be one of {DEVICES}, got {self.device!r}")
        if self.threads < 0:
            raise ValueError(f"threads must be >= 0, got {self.threads}")
        if not self.texture_tiling > 0:
            raise ValueError(f"texture_tiling must be > 0, got {self.texture_tiling}")


def derive_seed(dataset_seed: int, material_index: int, sun_index: int = -1) -> int:
    """A job's seed from (dataset seed, material index, sun index); 31-bit, Cycles-safe.

    ``sun_index=-1`` names the material itself (its sun draws and generator). Pure function:
    the same triple always gives the same seed, on every machine.
    """
    if dataset_seed < 0 or material_index < 0 or sun_index < -1:
        raise ValueError("seeds and indices must be non-negative")
    ss = np.random.SeedSequence([dataset_seed, material_index, sun_index + 1])
    return int(ss.generate_state(1, dtype=np.uint32)[0] & 0x7FFFFFFF)


@dataclass(frozen=True)
class RenderJob(_Serialisable):
    """One material under K suns: the unit of work a worker renders (all suns of a material)."""

    material_index: int
    material: MaterialSpec
    suns: tuple[Sun, ...]
    seeds: tuple[int, ...] = field(default=())

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> RenderJob:
        return cls(
            material_index=data["material_index"],
            material=MaterialSpec.from_dict(data["material"]),
            suns=tuple(Sun.from_dict(s) for s in data["suns"]),
            seeds=tuple(data["seeds"]),
        )
