"""What the camera sees of the shaderball's UV layout: per sub-pixel sample, the UV that the
camera ray hits on the material (ball shell and core), or nothing. Plain numpy, no ``bpy``.

With it, screen-space material maps are made without Blender (``trainer.rendering.mapping``): look
the textures up at every sub-sample's UV, as Cycles' image textures do, then average the
sub-samples of each pixel with Cycles' own pixel filter. That is what the render's AOVs are
(``render_jobs.blender.shading``): the expectation of the texture value under the pixel
filter, taken by Cycles with random samples, and here with a regular grid of
``supersample`` x ``supersample`` samples per pixel.

The pixel filter is Cycles' own (:mod:`render_jobs.pixel_filter`).

The layout depends on the resolution, the camera and the geometry, not on the material, the
sun or the samples per pixel: a store keeps one (``screen_uv.npz``), written once by the farm
from Blender, and a checkpoint carries its store's. The same render gives the per-pixel
geometry buffers (:mod:`render_jobs.screen_geometry`), kept in the same file.
"""

from __future__ import annotations

import io
import json
from dataclasses import dataclass, fields

import numpy as np

from render_jobs.pixel_filter import (
    FILTER_WIDTH,
    PIXEL_FILTER,
    blackman_harris,
    filter_image,
    filter_taps,
)
from render_jobs.screen_geometry import ScreenGeometry, ScreenGeometryError
from shaderball.errors import UserError

__all__ = [
    "FILTER_WIDTH",
    "PIXEL_FILTER",
    "ScreenUV",
    "ScreenUVError",
    "blackman_harris",
    "default_supersample",
    "filter_image",
    "filter_taps",
]

#: sub-samples per pixel side unless told otherwise (``tests/test_mapping.py`` holds the maps
#: made with it to Cycles' own AOVs)
DEFAULT_SUPERSAMPLE = 4
FILE = "screen_uv.npz"
#: the prefix of the geometry buffers' arrays in :data:`FILE`
GEOMETRY_PREFIX = "geometry_"


def default_supersample(resolution: int) -> int:
    """Sub-samples a pixel side for ``resolution``: 4 up to 256², fewer above (3 at 400²),
    where a pixel spans fewer texels: at least 1,024 sub-samples across the image."""
    return max(2, min(DEFAULT_SUPERSAMPLE, -(-1024 // resolution)))


class ScreenUVError(UserError, ValueError):
    """A screen UV layout that is unreadable or does not fit what it is used with."""


@dataclass(frozen=True)
class ScreenUV:
    """UV layout of the ball at ``resolution``² pixels, ``supersample``² sub-samples each.

    ``uv``: ``(S R, S R, 2) float32``, row 0 at the top: (u, v) of the material at each
    sub-sample's centre (u around, v pole to pole, as ``render_jobs.geometry`` lays them out;
    0 where ``hit`` is false). ``hit``: ``(S R, S R) bool``, the sub-sample sees the material.
    ``texture_tiling`` is the renderer's (repeats pole to pole, twice that around);
    ``geometry_hash`` names the scene it was rendered from
    (:func:`render_jobs.geometry.geometry_hash`, as a store's settings hold it).
    ``geometry``: the per-pixel geometry buffers of the same render
    (:class:`render_jobs.screen_geometry.ScreenGeometry`), or ``None`` in a layout rendered
    without them."""

    uv: np.ndarray
    hit: np.ndarray
    resolution: int
    supersample: int
    texture_tiling: float
    geometry_hash: str
    filter_width: float = FILTER_WIDTH
    pixel_filter: str = PIXEL_FILTER
    geometry: ScreenGeometry | None = None

    def __post_init__(self) -> None:
        n = self.resolution * self.supersample
        if self.uv.shape != (n, n, 2) or self.uv.dtype != np.float32:
            raise ScreenUVError(f"uv is {self.uv.dtype} {self.uv.shape}, not float32 {(n, n, 2)}")
        if self.hit.shape != (n, n) or self.hit.dtype != np.bool_:
            raise ScreenUVError(f"hit is {self.hit.dtype} {self.hit.shape}, not bool {(n, n)}")
        if self.pixel_filter != PIXEL_FILTER:
            raise ScreenUVError(f"pixel filter {self.pixel_filter!r} is not {PIXEL_FILTER}")
        if self.geometry is not None and self.geometry.resolution != self.resolution:
            raise ScreenUVError(
                f"geometry buffers are {self.geometry.resolution}², the layout {self.resolution}²"
            )

    def meta(self) -> dict:
        """Everything but the arrays (JSON-safe); the geometry's own under ``geometry``."""
        out = {f.name: getattr(self, f.name) for f in fields(self)}
        out = {k: v for k, v in out.items() if k not in ("uv", "hit", "geometry")}
        if self.geometry is not None:
            out["geometry"] = self.geometry.meta()
        return out

    def taps(self) -> np.ndarray:
        return filter_taps(self.supersample, self.filter_width)

    def coverage(self) -> np.ndarray:
        """``(R, R) float32``: the filtered hits, the mask AOV this layout predicts."""
        return filter_image(self.hit.astype(np.float32)[None], self.supersample, self.taps())[0]

    def to_bytes(self) -> bytes:
        """A compressed ``.npz`` (zip, CRC-checked on read) of the arrays and ``meta``."""
        buf = io.BytesIO()
        meta = np.frombuffer(json.dumps(self.meta()).encode(), np.uint8)
        geometry = {} if self.geometry is None else self.geometry.arrays()
        extra = {GEOMETRY_PREFIX + k: v for k, v in geometry.items()}
        np.savez_compressed(buf, uv=self.uv, hit=self.hit, meta=meta, **extra)
        return buf.getvalue()

    @classmethod
    def from_bytes(cls, data: bytes, where: str = "screen UV") -> ScreenUV:
        try:
            with np.load(io.BytesIO(data), allow_pickle=False) as z:
                meta = json.loads(z["meta"].tobytes())
                geo = meta.pop("geometry", None)
                if geo is not None:
                    n = len(GEOMETRY_PREFIX)
                    arrays = {k[n:]: z[k] for k in z.files if k.startswith(GEOMETRY_PREFIX)}
                    meta["geometry"] = ScreenGeometry.from_arrays(arrays, geo)
                return cls(uv=z["uv"], hit=z["hit"], **meta)
        except (ScreenUVError, ScreenGeometryError) as exc:
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
