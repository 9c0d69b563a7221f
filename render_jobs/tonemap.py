"""The display tonemap for previews and contact sheets (numpy).

``tonemap(x) = srgb_encode(y / (1 + y))`` with ``y = x * 2**exposure`` (per channel Reinhard,
then sRGB), mapping linear HDR radiance ``(3, H, W)`` to ``[0, 1]``. Default exposure +1 stop:
the sky-lit grey ground sits near mid-grey.
"""

from __future__ import annotations

import numpy as np

from render_jobs.materials.maps import linear_to_srgb, quantize_u8

DEFAULT_EXPOSURE = 1.0


def tonemap(radiance: np.ndarray, exposure: float = DEFAULT_EXPOSURE) -> np.ndarray:
    """Linear HDR ``(C, H, W)`` → display ``(C, H, W) float32`` in [0, 1]."""
    y = np.clip(np.asarray(radiance, dtype=np.float32), 0.0, None) * np.float32(2.0**exposure)
    return np.clip(linear_to_srgb(y / (1.0 + y)), 0.0, 1.0)


def to_uint8(image: np.ndarray) -> np.ndarray:
    """``(C, H, W)`` in [0, 1] (C = 1 or 3) → ``(H, W, 3) uint8``, C-contiguous (from a
    planar image, a copy of the bytes: image encoders read strided pixels slower)."""
    x = np.asarray(image, dtype=np.float32)
    if x.shape[0] == 1:
        x = np.repeat(x, 3, axis=0)
    return np.ascontiguousarray(quantize_u8(x.transpose(1, 2, 0)))
