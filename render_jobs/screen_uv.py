"""What the camera sees of the shaderball's UV layout: per sub-pixel sample, the UV that the
camera ray hits on the material (ball shell and core), or nothing. Plain numpy, no ``bpy``.

With it, screen-space material maps are made without Blender (``trainer.mapping``): look the
textures up at every sub-sample's UV, as Cycles' image textures do, then average the
sub-samples of each pixel with Cycles' own pixel filter. That is what the render's AOVs are
(``render_jobs.blender.shading``): the expectation of the texture value under the pixel
filter, taken by Cycles with random samples, and here with a regular grid of
``supersample`` x ``supersample`` samples per pixel.

Pixel filter: Cycles' Blackman-Harris of ``filter_width`` w (1.5 px, Blender's default and the
renderer's setting). Cycles builds its table over ``2 w``, so the window spans ±w pixels
around the pixel's centre, and it draws x and y offsets independently: the 2D filter is the
product of two 1D windows. :func:`filter_taps` integrates that window over each sub-sample's
cell, so a pixel is a ``3 S`` x ``3 S`` weighted sum of sub-samples (stride ``S``).

The layout depends on the resolution, the camera and the geometry, not on the material, the
sun or the samples per pixel: a store keeps one (``screen_uv.npz``), written once by the farm
from Blender, and a checkpoint carries its store's.
"""

from __future__ import annotations

import io
import json
import math
from dataclasses import asdict, dataclass

import numpy as np

#: Cycles' pixel filter as the renderer sets it (``pixel_filter_type``, ``filter_width``)
PIXEL_FILTER = "BLACKMAN_HARRIS"
FILTER_WIDTH = 1.5
#: sub-samples per pixel side unless told otherwise (measured against Cycles' AOVs:
#: docs/rendering.md, "Screen-space maps without Blender")
DEFAULT_SUPERSAMPLE = 4
FILE = "screen_uv.npz"


def default_supersample(resolution: int) -> int:
    """Sub-samples a pixel side for ``resolution``: 4 up to 256², fewer above (3 at 400²),
    where a pixel spans fewer texels: at least 1,024 sub-samples across the image."""
    return max(2, min(DEFAULT_SUPERSAMPLE, -(-1024 // resolution)))


class ScreenUVError(ValueError):
    """A screen UV layout that is unreadable or does not fit what it is used with."""


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


@dataclass(frozen=True)
class ScreenUV:
    """UV layout of the ball at ``resolution``² pixels, ``supersample``² sub-samples each.

    ``uv``: ``(S R, S R, 2) float32``, row 0 at the top: (u, v) of the material at each
    sub-sample's centre (u around, v pole to pole, as ``render_jobs.geometry`` lays them out;
    0 where ``hit`` is false). ``hit``: ``(S R, S R) bool``, the sub-sample sees the material.
    ``texture_tiling`` is the renderer's (repeats pole to pole, twice that around);
    ``geometry_hash`` names the scene it was rendered from
    (:func:`render_jobs.geometry.geometry_hash`, as a store's settings hold it)."""

    uv: np.ndarray
    hit: np.ndarray
    resolution: int
    supersample: int
    texture_tiling: float
    geometry_hash: str
    filter_width: float = FILTER_WIDTH
    pixel_filter: str = PIXEL_FILTER

    def __post_init__(self) -> None:
        n = self.resolution * self.supersample
        if self.uv.shape != (n, n, 2) or self.uv.dtype != np.float32:
            raise ScreenUVError(f"uv is {self.uv.dtype} {self.uv.shape}, not float32 {(n, n, 2)}")
        if self.hit.shape != (n, n) or self.hit.dtype != np.bool_:
            raise ScreenUVError(f"hit is {self.hit.dtype} {self.hit.shape}, not bool {(n, n)}")
        if self.pixel_filter != PIXEL_FILTER:
            raise ScreenUVError(f"pixel filter {self.pixel_filter!r} is not {PIXEL_FILTER}")

    def meta(self) -> dict:
        """Everything but the arrays (JSON-safe)."""
        return {k: v for k, v in asdict(self).items() if k not in ("uv", "hit")}

    def taps(self) -> np.ndarray:
        return filter_taps(self.supersample, self.filter_width)

    def coverage(self) -> np.ndarray:
        """``(R, R) float32``: the filtered hits, the mask AOV this layout predicts."""
        return filter_image(self.hit.astype(np.float32)[None], self.supersample, self.taps())[0]

    def to_bytes(self) -> bytes:
        """A compressed ``.npz`` (zip, CRC-checked on read) of the arrays and ``meta``."""
        buf = io.BytesIO()
        meta = np.frombuffer(json.dumps(self.meta()).encode(), np.uint8)
        np.savez_compressed(buf, uv=self.uv, hit=self.hit, meta=meta)
        return buf.getvalue()

    @classmethod
    def from_bytes(cls, data: bytes, where: str = "screen UV") -> ScreenUV:
        try:
            with np.load(io.BytesIO(data), allow_pickle=False) as z:
                meta = json.loads(z["meta"].tobytes())
                return cls(uv=z["uv"], hit=z["hit"], **meta)
        except ScreenUVError as exc:
            raise ScreenUVError(f"{where}: {exc}") from None
        except Exception as exc:  # noqa: BLE001 - zip, CRC, JSON and key errors alike
            raise ScreenUVError(f"{where}: not a readable screen UV layout ({exc})") from None

    def check_fits(self, settings: dict, where: str) -> None:
        """Raise naming the first setting in which the layout differs from a dataset's
        ``settings`` (a store's: ``resolution``, ``texture_tiling``, ``geometry_hash``)."""
        resolution, texture_tiling = settings["resolution"], settings.get("texture_tiling", 2.0)
        if self.resolution != resolution:
            raise ScreenUVError(
                f"{where}: the screen UV layout is for {self.resolution}², not {resolution}²"
            )
        if self.texture_tiling != texture_tiling:
            raise ScreenUVError(
                f"{where}: the screen UV layout has texture tiling {self.texture_tiling}, "
                f"not {texture_tiling}"
            )
        scene = settings.get("geometry_hash")
        if scene is not None and self.geometry_hash != scene:
            raise ScreenUVError(
                f"{where}: the screen UV layout was rendered from another scene "
                f"(geometry {self.geometry_hash[:12]}, not {scene[:12]})"
            )


def filter_image(x: np.ndarray, supersample: int, taps: np.ndarray) -> np.ndarray:
    """Sub-sampled ``(C, S R, S R)`` → ``(C, R, R) float32`` with the separable ``taps``
    (numpy reference of what ``trainer.mapping`` does with convolutions)."""
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
