"""The four Cook-Torrance texture maps of one material, as the renderer consumes them."""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass

import numpy as np

from render_jobs.errors import MaterialError

MAP_CHANNELS = {"diffuse": 3, "specular": 3, "roughness": 1, "normal": 3}


@dataclass(frozen=True)
class MaterialMaps:
    """Texture maps, each ``(H, W, C) float32`` in [0, 1], all the same H x W, in image-file
    order (row 0 is the top of the texture, v = 1; column 0 is u = 0).

    - ``diffuse`` (C=3), ``specular`` (C=3): sRGB-encoded albedo / specular colour, as stored
      in 8-bit PNG maps (Blender decodes sRGB when it samples them);
    - ``roughness`` (C=1): GGX roughness r, linear (alpha = r**2);
    - ``normal`` (C=3): tangent-space normal encoded as (n + 1) / 2, linear, OpenGL (+Y up).
    """

    diffuse: np.ndarray
    specular: np.ndarray
    roughness: np.ndarray
    normal: np.ndarray
    source_id: str = ""

    def __post_init__(self) -> None:
        shape = None
        for name, channels in MAP_CHANNELS.items():
            arr = getattr(self, name)
            where = self.source_id or "material"
            if arr.ndim != 3 or arr.shape[2] != channels:
                raise MaterialError(
                    f"{where}: {name} map must have shape (H, W, {channels}), got {arr.shape}"
                )
            if arr.dtype != np.float32:
                raise MaterialError(f"{where}: {name} map must be float32, got {arr.dtype}")
            if shape is None:
                shape = arr.shape[:2]
            elif arr.shape[:2] != shape:
                raise MaterialError(
                    f"{where}: {name} map is {arr.shape[1]}x{arr.shape[0]}, "
                    f"others are {shape[1]}x{shape[0]}"
                )
            check_values(where, name, arr)

    @property
    def size(self) -> tuple[int, int]:
        """(height, width) in texels."""
        return self.diffuse.shape[0], self.diffuse.shape[1]


@dataclass(frozen=True)
class MapBytes:
    """A material's maps as the 8-bit values Blender's image textures hold: map name to
    ``(H, W, C) uint8``, each value ``floor(v * 255 + 0.5)`` (float32 arithmetic) of
    :class:`MaterialMaps`' float. A render worker sends these to its Blender process: the
    same textures in a quarter of the floats' bytes (160 MB for a 4K material, not 640 MB)."""

    arrays: dict[str, np.ndarray]
    source_id: str = ""

    @classmethod
    def of(cls, maps: MaterialMaps) -> MapBytes:
        arrays = {name: quantize_u8(getattr(maps, name)) for name in MAP_CHANNELS}
        return cls(arrays, maps.source_id)

    @property
    def size(self) -> tuple[int, int]:
        """(height, width) in texels."""
        return self.arrays["diffuse"].shape[:2]


def check_values(where: str, name: str, arr: np.ndarray) -> None:
    """Raise :class:`MaterialError` unless every value of ``name`` map (or a band of its rows)
    is finite and in [0, 1]."""
    # min and max carry a NaN or an infinity through: two passes, no temporaries
    lo, hi = float(arr.min()), float(arr.max())
    if not (math.isfinite(lo) and math.isfinite(hi)):
        raise MaterialError(f"{where}: {name} map holds NaN or Inf values")
    if lo < 0.0 or hi > 1.0:
        raise MaterialError(
            f"{where}: {name} map values must lie in [0, 1], got [{lo:.3g}, {hi:.3g}]"
        )


def quantize_u8(x: np.ndarray) -> np.ndarray:
    """Values in [0, 1] (float32) → ``uint8``, ``floor(clamp(x, 0, 1) · 255 + 0.5)`` in
    float32: the one 8-bit rounding of textures (:class:`MapBytes`), stored maps
    (``storage.schema.encode_maps``) and pictures (``render_jobs.tonemap.to_uint8``)."""
    out = np.clip(x, 0.0, 1.0)  # a copy, then scaled in place: one float temporary
    out *= 255.0
    out += 0.5
    return out.astype(np.uint8)


def srgb_to_linear(x: np.ndarray) -> np.ndarray:
    """IEC 61966-2-1 sRGB decode, elementwise, float32.

    Written as in-place ufuncs (one output array, the low segment written over the curve where
    it applies): the values of ``np.where(x <= 0.04045, x / 12.92, ((x + 0.055) / 1.055) **
    2.4)`` in float32, bit for bit, at about half its time and memory."""
    x = np.asarray(x, dtype=np.float32)
    out = np.add(x, np.float32(0.055), out=np.empty_like(x))
    out /= np.float32(1.055)
    np.power(out, np.float32(2.4), out=out)
    np.divide(x, np.float32(12.92), out=out, where=x <= np.float32(0.04045))
    return out


def linear_to_srgb(x: np.ndarray) -> np.ndarray:
    """IEC 61966-2-1 sRGB encode, elementwise, float32 (negatives clamp to 0); in-place ufuncs,
    the values of the ``np.where`` form bit for bit (:func:`srgb_to_linear`)."""
    x = np.clip(np.asarray(x, dtype=np.float32), np.float32(0.0), None)
    out = np.power(x, np.float32(1 / 2.4), out=np.empty_like(x))
    out *= np.float32(1.055)
    out -= np.float32(0.055)
    np.multiply(x, np.float32(12.92), out=out, where=x <= np.float32(0.0031308))
    return out


@functools.cache
def srgb_table(bits: int) -> np.ndarray:
    """:func:`srgb_to_linear` of every level of ``bits``-bit (8 or 16) integer samples, as
    ``images.Image.rows`` scales them (``v / (2**bits - 1)`` in float32): indexed by the
    samples, it gives the decode of their floats exactly, at the cost of one gather."""
    levels = np.arange(1 << bits, dtype=np.float32)
    levels /= np.float32((1 << bits) - 1)
    table = srgb_to_linear(levels)
    table.flags.writeable = False
    return table
