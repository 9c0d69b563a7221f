"""Random uniform (spatially constant) materials.

Ranges, drawn independently from the generator:

- diffuse: sRGB colour, each channel uniform in [0.02, 0.95];
- specular: grey level g uniform in [0.02, 0.9], tinted by mixing 20% of a random colour in,
  so most materials are dielectric-like and a few look metallic;
- roughness: uniform in [0.05, 1.0] (GGX alpha = r**2, so glossy to fully rough);
- normal: tilted from +Z by an angle uniform in [0°, 15°], azimuth uniform in [0°, 360°).
"""

from __future__ import annotations

import math

import numpy as np

from render_jobs.materials.maps import MaterialMaps
from render_jobs.specs import UniformValues

UNIFORM_MAP_SIZE = 4  # texels: the maps are constant, so a tiny texture is exact


def sample_uniform(rng: np.random.Generator) -> UniformValues:
    """Draw one uniform material's values."""
    diffuse = rng.uniform(0.02, 0.95, size=3)
    grey = rng.uniform(0.02, 0.9)
    tint = rng.uniform(0.0, 1.0, size=3)
    specular = np.clip(0.8 * grey + 0.2 * grey * tint / max(tint.max(), 1e-6), 0.0, 1.0)
    return UniformValues(
        diffuse=tuple(float(c) for c in diffuse),  # type: ignore[arg-type]
        specular=tuple(float(c) for c in specular),  # type: ignore[arg-type]
        roughness=float(rng.uniform(0.05, 1.0)),
        normal_tilt_deg=float(rng.uniform(0.0, 15.0)),
        normal_azimuth_deg=float(rng.uniform(0.0, 360.0)),
    )


def uniform_maps(values: UniformValues, source_id: str = "uniform") -> MaterialMaps:
    """Constant maps (4x4 texels) for ``values``."""
    s = UNIFORM_MAP_SIZE
    tilt, az = math.radians(values.normal_tilt_deg), math.radians(values.normal_azimuth_deg)
    n = np.array([math.sin(tilt) * math.cos(az), math.sin(tilt) * math.sin(az), math.cos(tilt)])

    def const(v) -> np.ndarray:
        v = np.atleast_1d(np.asarray(v, dtype=np.float32))
        return np.broadcast_to(v, (s, s, v.size)).astype(np.float32)

    return MaterialMaps(
        diffuse=const(values.diffuse),
        specular=const(values.specular),
        roughness=const(values.roughness),
        normal=const((n + 1.0) / 2.0),
        source_id=source_id,
    )
