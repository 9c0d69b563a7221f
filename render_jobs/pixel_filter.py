"""Cycles' pixel filter, as the renderer sets it, and its discrete form over sub-samples.

Cycles' Blackman-Harris of ``filter_width`` w (1.5 px, Blender's default and the renderer's
setting). Cycles builds its table over ``2 w``, so the window spans ±w pixels around the
pixel's centre, and it draws x and y offsets independently: the 2D filter is the product of
two 1D windows. :func:`filter_taps` integrates that window over each sub-sample's cell, so a
pixel is a ``3 S`` x ``3 S`` weighted sum of sub-samples (stride ``S``).
"""

from __future__ import annotations

import math

import numpy as np

#: Cycles' pixel filter as the renderer sets it (``pixel_filter_type``, ``filter_width``)
PIXEL_FILTER = "BLACKMAN_HARRIS"
FILTER_WIDTH = 1.5


def blackman_harris(x: np.ndarray, width: float = FILTER_WIDTH) -> np.ndarray:
    """Cycles' 1D Blackman-Harris window at offsets ``x`` (pixels) for ``filter_width``
    ``width``: support ``[-width, width]``, 0 outside."""
    x = np.asarray(x, dtype=np.float64)
    v = 2 * math.pi * (x / (2 * width) + 0.5)
    f = 0.35875 - 0.48829 * np.cos(v) + 0.14128 * np.cos(2 * v) - 0.01168 * np.cos(3 * v)
    return np.where(np.abs(x) <= width, f, 0.0)


def filter_taps(supersample: int, width: float = FILTER_WIDTH) -> np.ndarray:
    """1D weights ``(3 S,) float64`` summing to 1: tap ``j`` weighs the sub-sample ``S p - S + j``
    for pixel ``p`` (``S`` = ``supersample``), its window integrated over the sub-sample's cell.
    Needs ``width`` <= 1.5 pixels (the taps cover ±1.5)."""
    if supersample < 1:
        raise ValueError(f"supersample must be >= 1, not {supersample}")
    if not 0 < width <= 1.5:
        raise ValueError(f"filter width must lie in (0, 1.5], not {width}")
    s = supersample
    centres = (np.arange(3 * s) - s + 0.5) / s - 0.5  # sub-sample offsets from the pixel centre
    fine = 64  # points per cell for the integral
    within = (np.arange(fine) + 0.5) / fine - 0.5
    taps = blackman_harris(centres[:, None] + within[None, :] / s, width).mean(1)
    return taps / taps.sum()


def filter_image(x: np.ndarray, supersample: int, taps: np.ndarray) -> np.ndarray:
    """Sub-sampled ``(C, S R, S R)`` → ``(C, R, R) float32`` with the separable ``taps``
    (numpy reference of what ``trainer.rendering.mapping`` does with convolutions)."""
    s, k = supersample, len(taps)
    c, n, _ = x.shape
    r = n // s
    padded = np.pad(x.astype(np.float64), ((0, 0), (s, s), (s, s)))
    rows = np.zeros((c, r, n + 2 * s))
    for j in range(k):  # along y
        rows += taps[j] * padded[:, j : j + s * r : s, :]
    out = np.zeros((c, r, r))
    for j in range(k):  # along x
        out += taps[j] * rows[:, :, j : j + s * r : s]
    return out.astype(np.float32)
