"""What a render job returns: plain numpy data (no ``bpy``), picklable across processes."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from render_jobs.specs import Sun


@dataclass
class ScreenMaps:
    """The material maps as the camera sees them (one per material; they ignore the sun).

    Each is ``(C, H, W) float32``, anti-aliased with the render's pixel filter and multiplied
    by pixel coverage (0 off the material; divide by ``mask`` to un-premultiply):

    - ``diffuse`` (3), ``specular`` (3): linear reflectance (sRGB map values decoded);
    - ``roughness`` (1): GGX roughness r; ``normal`` (3): tangent-space normal map values,
      encoded (n + 1) / 2, as UV-mapped on the ball (the geometry's own normal is not in it);
    - ``mask`` (1): coverage of the material (ball shell and core) in [0, 1].
    """

    diffuse: np.ndarray
    specular: np.ndarray
    roughness: np.ndarray
    normal: np.ndarray
    mask: np.ndarray

    NAMES = ("diffuse", "specular", "roughness", "normal", "mask")

    def as_dict(self) -> dict[str, np.ndarray]:
        return {name: getattr(self, name) for name in self.NAMES}


@dataclass
class SunRender:
    """One Cycles render: ``radiance`` is ``(3, H, W) float32`` linear HDR (scene-referred,
    Rec.709 primaries), no denoising, ``samples`` paths per pixel, Cycles seed ``seed``.

    ``timings`` (seconds): ``scene`` (Python-side scene changes), ``render`` (the whole
    ``render()`` call: sync, path tracing, EXR write), ``path_tracing`` (first to last
    sample, from Cycles' own progress), ``exr_read``; ``total`` is their wall time.
    """

    sun: Sun
    seed: int
    radiance: np.ndarray
    timings: dict[str, float] = field(default_factory=dict)

    @property
    def seconds(self) -> float:
        return self.timings.get("total", 0.0)


@dataclass
class MaterialRender:
    """All suns of one material: its screen maps once, then one render per sun."""

    maps: ScreenMaps
    renders: list[SunRender]
    geometry_hash: str
    rss_bytes: int = 0
    material_seconds: float = 0.0  # texture upload
