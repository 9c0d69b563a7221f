"""Sun sampling and the sun lamp's strength and colour (no ``bpy``).

Blender's Hosek-Wilkie sky has no sun disc, so the renderer adds a Sun lamp in the sky's sun
direction. Its irradiance and colour come from a clear-sky extinction model:

- relative optical air mass ``m`` from the zenith angle (Kasten & Young 1989);
- per-wavelength optical depth = Rayleigh scattering (Bodhaine et al. 1999 fit,
  ``0.008569 λ⁻⁴ (1 + 0.0113 λ⁻² + 0.00013 λ⁻⁴)``, λ in µm) plus aerosols by Ångström's law
  ``β λ^-1.3`` with β from turbidity as in Preetham et al. 1999 (``β = 0.04608 T − 0.04586``);
- transmittance ``t(λ) = exp(−m τ(λ))`` at 680 / 550 / 440 nm for R / G / B.

Lamp colour = t / max(t) (warmer when low or hazy); lamp strength = ``SUN_ZENITH_IRRADIANCE``
× t(550 nm) / t_ref, where t_ref is the transmittance of a zenith sun at turbidity 2, so the
sun dims as it sets and as turbidity rises. ``SUN_ZENITH_IRRADIANCE`` sets the direct-to-sky
balance: see its comment for how it was chosen.

Sampling: directions uniform in solid angle over the upper hemisphere above
``min_elevation_deg``; turbidity uniform in ``turbidity_range`` (inside Hosek-Wilkie's [1, 10]).
"""

from __future__ import annotations

import math

import numpy as np

from render_jobs.specs import Sun

#: Default sun sampling (documented in docs/rendering.md): 5 suns per material, at least 10° up,
#: turbidity in [2, 10] (the authors' tool offers 2, 3, 6 and 10).
DEFAULT_SUNS = 5
DEFAULT_MIN_ELEVATION_DEG = 10.0
DEFAULT_TURBIDITY_RANGE = (2.0, 10.0)

#: Blender Sun-lamp strength (W/m², irradiance at normal incidence) of a zenith sun at
#: turbidity 2; it sets the direct-to-sky balance. Measured against Blender 4.5's Hosek-Wilkie
#: sky (strength 1, ground albedo 0.3), horizontal irradiance, direct / sky: 7.8 at 80° and
#: T 2, 5.6 at 60° and T 3, 4.1 at 40° and T 3, 0.6 at 20° and T 6 (sky alone ≈ 0.24-0.27),
#: the range of real clear to hazy skies (``python -m benchmarks.sky``).
SUN_ZENITH_IRRADIANCE = 2.0

#: Angular diameter of the sun's disc, degrees (soft shadow edges).
SUN_ANGLE_DEG = 0.53

_WAVELENGTHS_UM = np.array([0.680, 0.550, 0.440])


def air_mass(elevation_deg: float) -> float:
    """Relative optical air mass (Kasten & Young 1989); 1 at zenith, about 38 at the horizon."""
    zenith = 90.0 - elevation_deg
    return 1.0 / (math.cos(math.radians(zenith)) + 0.50572 * (96.07995 - zenith) ** -1.6364)


def transmittance(elevation_deg: float, turbidity: float) -> np.ndarray:
    """Direct-beam transmittance at R, G, B wavelengths: ``(3,) float64`` in (0, 1]."""
    lam = _WAVELENGTHS_UM
    tau_rayleigh = 0.008569 * lam**-4 * (1 + 0.0113 * lam**-2 + 0.00013 * lam**-4)
    beta = max(0.04608 * turbidity - 0.04586, 0.0)
    tau_aerosol = beta * lam**-1.3
    return np.exp(-air_mass(elevation_deg) * (tau_rayleigh + tau_aerosol))


_T_REF = transmittance(90.0, 2.0)[1]


def sun_lamp(sun: Sun) -> tuple[float, tuple[float, float, float]]:
    """(strength, linear RGB colour with max 1) of the Sun lamp for ``sun``."""
    t = transmittance(sun.elevation_deg, sun.turbidity)
    strength = SUN_ZENITH_IRRADIANCE * float(t[1] / _T_REF)
    colour = t / t.max()
    return strength, (float(colour[0]), float(colour[1]), float(colour[2]))


def sample_suns(
    rng: np.random.Generator,
    k: int = DEFAULT_SUNS,
    min_elevation_deg: float = DEFAULT_MIN_ELEVATION_DEG,
    turbidity_range: tuple[float, float] = DEFAULT_TURBIDITY_RANGE,
) -> list[Sun]:
    """Draw ``k`` suns: directions uniform in solid angle above ``min_elevation_deg``."""
    if k < 1:
        raise ValueError(f"need at least one sun, got {k}")
    if not 0.0 <= min_elevation_deg < 90.0:
        raise ValueError(f"min elevation must lie in [0, 90), got {min_elevation_deg}")
    lo, hi = turbidity_range
    if not 1.0 <= lo <= hi <= 10.0:
        raise ValueError(f"turbidity range must lie inside [1, 10], got {turbidity_range}")
    z_min = math.sin(math.radians(min_elevation_deg))
    suns = []
    for _ in range(k):
        z = rng.uniform(max(z_min, 1e-3), 1.0)
        phi = rng.uniform(0.0, 2.0 * math.pi)
        r = math.sqrt(max(0.0, 1.0 - z * z))
        direction = (r * math.cos(phi), r * math.sin(phi), z)
        norm = math.sqrt(sum(c * c for c in direction))
        suns.append(
            Sun(
                direction=tuple(c / norm for c in direction),  # type: ignore[arg-type]
                turbidity=float(rng.uniform(lo, hi)),
            )
        )
    return suns


SUN_STREAM = 0x5A11  # tags the sun draws' seed stream, apart from the material's own seed


def suns_for_material(
    dataset_seed: int,
    material_index: int,
    k: int = DEFAULT_SUNS,
    min_elevation_deg: float = DEFAULT_MIN_ELEVATION_DEG,
    turbidity_range: tuple[float, float] = DEFAULT_TURBIDITY_RANGE,
) -> list[Sun]:
    """The ``k`` suns of material ``material_index`` in a dataset seeded ``dataset_seed``.

    Drawn from their own seed stream (not the material generator's), so the same triple gives
    the same suns on every machine, whatever else is drawn.
    """
    seq = np.random.SeedSequence([dataset_seed, material_index, SUN_STREAM])
    return sample_suns(np.random.default_rng(seq), k, min_elevation_deg, turbidity_range)


def sun_from_angles(elevation_deg: float, azimuth_deg: float, turbidity: float) -> Sun:
    """A sun from elevation and azimuth (degrees, azimuth from +X towards +Y)."""
    el, az = math.radians(elevation_deg), math.radians(azimuth_deg)
    d = (math.cos(el) * math.cos(az), math.cos(el) * math.sin(az), math.sin(el))
    return Sun(direction=d, turbidity=turbidity)


def sun_sweep(sun: Sun, n: int) -> list[Sun]:
    """``n`` suns a full turn around the zenith from ``sun``, at its elevation and turbidity,
    evenly spaced in azimuth (the first is ``sun``'s azimuth)."""
    if n < 1:
        raise ValueError(f"a sweep needs at least one sun, not {n}")
    return [
        sun_from_angles(sun.elevation_deg, sun.azimuth_deg + 360.0 * k / n, sun.turbidity)
        for k in range(n)
    ]
