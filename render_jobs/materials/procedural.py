"""Procedural SVBRDFs in numpy: seeded, tileable, at any map resolution.

Every pattern lives on the unit torus, so maps tile without seams, and every random draw is
made independently of the output size, so ``procedural_maps(seed, 256)`` is a resampling of
``procedural_maps(seed, 1024)``. Patterns (one or two chosen per material):

- ``noise``: fractal (1/f^β) noise synthesised in the Fourier domain from seeded coefficients;
- ``cells``: Worley cellular noise (distance to the nearest of a few dozen points), with
  per-cell colour ids and crack lines (F2 − F1);
- ``tiles``: running-bond tiles / bricks with grout, bevelled, per-tile tint;
- ``scratches``: thin random line segments (rougher, brighter or darker, grooved).

A height field combines them; normals come from its periodic gradient. Diffuse mixes two
random palette colours by the pattern, specular is dielectric-grey (or tinted for about a
quarter of the materials, which look metallic with a dark diffuse), roughness follows the
pattern around a random base.
"""

from __future__ import annotations

import colorsys

import numpy as np

from render_jobs.materials.maps import MaterialMaps

DEFAULT_MAP_RESOLUTION = 256
_SPECTRUM = 64  # noise coefficients cover frequencies -32..31 cycles per tile


def _grid(n: int) -> tuple[np.ndarray, np.ndarray]:
    c = (np.arange(n, dtype=np.float32) + 0.5) / n
    return np.meshgrid(c, c, indexing="xy")  # u (x, columns), v (y, rows)


def _normalise(x: np.ndarray) -> np.ndarray:
    lo, hi = np.percentile(x, [1, 99])
    return np.clip((x - lo) / max(hi - lo, 1e-8), 0.0, 1.0).astype(np.float32)


def fractal_noise(rng: np.random.Generator, n: int, beta: float) -> np.ndarray:
    """Tileable 1/f^beta noise, ``(n, n) float32`` in [0, 1]."""
    k = _SPECTRUM
    coeffs = rng.standard_normal((k, k)) + 1j * rng.standard_normal((k, k))
    f = np.fft.fftfreq(k, 1.0 / k)
    radius = np.hypot(*np.meshgrid(f, f, indexing="xy"))
    radius[0, 0] = np.inf
    coeffs = coeffs * radius**-beta
    spectrum = np.zeros((n, n), dtype=np.complex128)
    keep = min(k, n) // 2
    idx = np.r_[0:keep, -keep:0]
    spectrum[np.ix_(idx, idx)] = coeffs[np.ix_(idx, idx)]
    return _normalise(np.fft.ifft2(spectrum).real)


def _torus_delta(a: np.ndarray, b: float) -> np.ndarray:
    return (a - b + 0.5) % 1.0 - 0.5


def cells(rng: np.random.Generator, n: int, count: int) -> tuple[np.ndarray, np.ndarray]:
    """Worley noise on the torus: (F2 − F1 crack field in [0, 1], per-cell id in [0, 1))."""
    u, v = _grid(n)
    points = rng.uniform(0.0, 1.0, size=(count, 2))
    ids = rng.uniform(0.0, 1.0, size=count).astype(np.float32)
    f1 = np.full((n, n), np.inf, np.float32)
    f2 = np.full((n, n), np.inf, np.float32)
    cell = np.zeros((n, n), np.float32)
    for (px, py), cid in zip(points, ids, strict=True):
        d = np.hypot(_torus_delta(u, px), _torus_delta(v, py))
        closer = d < f1
        f2 = np.where(closer, f1, np.minimum(f2, d))
        cell = np.where(closer, cid, cell)
        f1 = np.where(closer, d, f1)
    crack = np.clip((f2 - f1) * np.sqrt(count) * 4.0, 0.0, 1.0)
    return crack.astype(np.float32), cell


def tiles(rng: np.random.Generator, n: int) -> tuple[np.ndarray, np.ndarray]:
    """Running-bond tiles: (bevelled height in [0, 1], per-tile id in [0, 1))."""
    u, v = _grid(n)
    cols = int(rng.integers(2, 7))
    rows = cols * int(rng.integers(1, 3))
    grout = rng.uniform(0.004, 0.012)  # grout width, tile widths of the whole map (uv units)
    offset = rng.choice([0.0, 0.5])
    row = np.floor(v * rows)
    x = u * cols + offset * (row % 2)
    col = np.floor(x) % cols
    fx, fy = x % 1.0, (v * rows) % 1.0
    edge = np.minimum(np.minimum(fx, 1 - fx) / cols, np.minimum(fy, 1 - fy) / rows)
    height = np.clip((edge - grout / 2) / grout, 0.0, 1.0)
    table = rng.uniform(0.0, 1.0, size=(rows, cols)).astype(np.float32)
    ids = table[row.astype(int) % rows, col.astype(int)]
    return height.astype(np.float32), ids


def scratches(rng: np.random.Generator, n: int, count: int) -> np.ndarray:
    """Thin random segments on the torus: coverage in [0, 1], ``(n, n) float32``."""
    u, v = _grid(n)
    out = np.zeros((n, n), np.float32)
    width = rng.uniform(0.6, 1.6) / 256.0
    for _ in range(count):
        p0 = rng.uniform(0.0, 1.0, size=2)
        angle = rng.uniform(0.0, np.pi)
        length = rng.uniform(0.05, 0.4)
        d = np.array([np.cos(angle), np.sin(angle)]) * length
        rx, ry = _torus_delta(u, p0[0]), _torus_delta(v, p0[1])
        t = np.clip((rx * d[0] + ry * d[1]) / (length * length), 0.0, 1.0)
        dist = np.hypot(rx - t * d[0], ry - t * d[1])
        out = np.maximum(out, np.clip(1.0 - dist / width, 0.0, 1.0) * rng.uniform(0.4, 1.0))
    return out


def _blur(x: np.ndarray, sigma_texels: float) -> np.ndarray:
    n = x.shape[0]
    f = np.fft.fftfreq(n)
    fx, fy = np.meshgrid(f, f, indexing="xy")
    g = np.exp(-2.0 * (np.pi * sigma_texels) ** 2 * (fx**2 + fy**2))
    return np.fft.ifft2(np.fft.fft2(x) * g).real.astype(np.float32)


def normals_from_height(height: np.ndarray, bump: float) -> np.ndarray:
    """Tangent-space normals from a periodic height field (``bump`` in tile widths).

    Returns ``(n, n, 3) float32`` encoded as (n + 1) / 2, OpenGL convention (+Y = +v).
    """
    n = height.shape[0]
    # image order: columns run along +u, rows along -v (row 0 is the top, v = 1)
    dhdu = (np.roll(height, -1, axis=1) - np.roll(height, 1, axis=1)) * (n / 2.0) * bump
    dhdv = (np.roll(height, 1, axis=0) - np.roll(height, -1, axis=0)) * (n / 2.0) * bump
    normal = np.stack([-dhdu, -dhdv, np.ones_like(height)], axis=-1)
    normal /= np.linalg.norm(normal, axis=-1, keepdims=True)
    return ((normal + 1.0) / 2.0).astype(np.float32)


def _colour(rng: np.random.Generator) -> np.ndarray:
    h = rng.uniform(0.0, 1.0)
    s = rng.uniform(0.0, 0.8) ** 1.5
    v = rng.uniform(0.15, 0.95)
    return np.array(colorsys.hsv_to_rgb(h, s, v), dtype=np.float32)


PATTERNS = ("noise", "cells", "tiles", "scratches")


def procedural_maps(seed: int, resolution: int = DEFAULT_MAP_RESOLUTION) -> MaterialMaps:
    """The procedural material for ``seed`` at ``resolution`` x ``resolution`` texels."""
    if resolution < 8:
        raise ValueError(f"procedural map resolution must be >= 8, got {resolution}")
    n = resolution
    rng = np.random.default_rng(seed)
    # draw every random stream from its own child generator so that adding a pattern
    # never shifts the others
    streams = [np.random.default_rng(s) for s in np.random.SeedSequence(seed).spawn(8)]
    pattern = PATTERNS[int(rng.integers(len(PATTERNS)))]
    detail = fractal_noise(streams[0], n, beta=rng.uniform(1.2, 2.2))
    fine = fractal_noise(streams[1], n, beta=rng.uniform(0.6, 1.0))
    if pattern == "noise":
        mask = (detail > rng.uniform(0.35, 0.65)).astype(np.float32)
        mask = _blur(mask, n / 256.0)
        height = 0.7 * detail + 0.3 * fine
        ids = detail
    elif pattern == "cells":
        crack, ids = cells(streams[2], n, int(rng.integers(8, 40)))
        mask = ids
        height = 0.8 * crack + 0.2 * fine
    elif pattern == "tiles":
        height, ids = tiles(streams[3], n)
        height = _blur(height, n / 512.0)
        mask = 1.0 - height
        height = 0.85 * height + 0.15 * fine
    else:  # scratches over noise
        mask = detail
        ids = detail
        height = 0.3 * detail
    scratch = scratches(streams[4], n, int(rng.integers(0, 25 if pattern == "scratches" else 6)))
    height = np.clip(height - 0.5 * scratch, 0.0, 1.0)

    metallic = rng.uniform() < 0.25
    c1, c2 = _colour(streams[5]), _colour(streams[5])
    m = mask[..., None]
    tint = (ids[..., None] - 0.5) * rng.uniform(0.0, 0.3)
    diffuse = (1 - m) * c1 + m * c2
    diffuse = diffuse * (0.85 + 0.3 * fine[..., None]) + tint
    if metallic:
        diffuse *= 0.15
        specular = np.broadcast_to(_colour(streams[6]) * 0.3 + 0.65, diffuse.shape)
    else:
        grey = rng.uniform(0.1, 0.5)
        specular = np.full(diffuse.shape, grey, np.float32)
    specular = specular * (1.0 - 0.4 * scratch[..., None] * rng.uniform(-1, 1))
    base = rng.uniform(0.1, 0.8)
    rough = base + rng.uniform(-0.3, 0.3) * (mask - 0.5) + 0.15 * (fine - 0.5)
    rough = rough + scratch * rng.uniform(-0.3, 0.4)

    return MaterialMaps(
        diffuse=np.clip(diffuse, 0.0, 1.0).astype(np.float32),
        specular=np.clip(specular, 0.0, 1.0).astype(np.float32),
        roughness=np.clip(rough, 0.02, 1.0).astype(np.float32)[..., None],
        normal=normals_from_height(height, bump=rng.uniform(0.004, 0.02)),
        source_id=f"procedural:seed={seed}:{pattern}",
    )
