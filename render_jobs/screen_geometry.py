"""What the fixed camera sees of the scene's geometry, per pixel: the constant buffers a
network can take beside the material maps. Plain numpy, no ``bpy``.

The camera, the shaderball, its stand and the floor never move, so what each pixel sees of
them is the same in every render. Blender renders it once, in the same supersampled pass as
the screen UV layout (``render_jobs.screen_uv``), and the sub-samples are filtered with
Cycles' pixel filter into per-pixel buffers, all ``float32``:

- ``position (3, R, R)``: camera-space position of what the pixel sees (metres; the camera
  looks down -z, x right, y up), weighted by the pixel's coverage of surfaces (0 for sky);
- ``normal (3, R, R)``: camera-space shading normal (the smooth-shaded surface normal,
  before any normal map), weighted the same way;
- ``tangent``, ``bitangent (3, R, R)``: camera-space directions that a tangent-space normal
  map's x and y mean on the material, as Blender's Normal Map node takes them (each is that
  node's output for a map of pure +x or +y), weighted by the material's coverage;
- ``parts (P, R, R)``: the pixel's coverage of each of :data:`PARTS`, summing to 1.

``camera_to_world`` (3x3, columns the camera's x, y, z axes in world space) and
``camera_location`` bring the buffers to world space, and the sun into camera space;
``occluders`` (:func:`render_jobs.geometry.occluders`) and ``materials``
(:data:`SCENE_MATERIALS`) describe the scene for shading it without Blender.
"""

from __future__ import annotations

import copy
from dataclasses import dataclass, field

import numpy as np

from render_jobs.geometry import occluders
from render_jobs.pixel_filter import filter_image
from render_jobs.specs import CAMERA, Camera
from shaderball.errors import UserError

#: what a pixel can see, in the order of the ``parts`` channels: the sky (nothing hit), the
#: floor, the stand, the ball's outer shell, its ring (the shell's inner face and the rims of
#: the cut), and the core the cut reveals
PARTS = ("sky", "floor", "stand", "ball", "ring", "core")
#: Blender's object pass index of each object: the index in :data:`PARTS` of the part its
#: surface is (the shell's faces inside :data:`RING_RADIUS` are the ring)
PASS_INDEX = {"ground": 1, "pedestal": 2, "shell": 3, "core": 5}
#: shell points nearer the centre than this are on its inner face or its rims
RING_RADIUS = 0.975
ARRAYS = ("position", "normal", "tangent", "bitangent", "parts")
#: the fixed materials of the floor and the stand, as the renderer builds them: diffuse and
#: specular reflectance (linear grey) and GGX roughness
SCENE_MATERIALS = {
    "floor": {"diffuse": 0.35, "specular": 0.0, "roughness": 1.0},
    "stand": {"diffuse": 0.06, "specular": 0.25, "roughness": 0.35},
}


class ScreenGeometryError(UserError, ValueError):
    """Geometry buffers that are unreadable or do not fit what they are used with."""


def camera_to_world(camera: Camera = CAMERA) -> np.ndarray:
    """``(3, 3) float64``: columns are the camera's x (right), y (up) and z (backwards) axes
    in world space, as Blender's track-to (-Z forward, Y up) orients the camera."""
    forward = np.subtract(camera.look_at, camera.location).astype(np.float64)
    z = -forward / np.linalg.norm(forward)
    x = np.cross([0.0, 0.0, 1.0], z)
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    return np.stack([x, y, z], 1)


def half_width(camera: Camera = CAMERA) -> float:
    """Tangent of half the horizontal field of view (sensor fit horizontal, square image)."""
    return camera.sensor_mm / (2.0 * camera.lens_mm)


def camera_rays(n: int, t: float) -> np.ndarray:
    """``(n, n, 3) float64`` unit camera-space directions through the centres of an ``n``²
    grid over the image (row 0 at the top), for a camera whose half field of view has the
    tangent ``t`` (:func:`half_width`)."""
    c = ((np.arange(n) + 0.5) / n * 2.0 - 1.0) * t
    x, y = np.meshgrid(c, -c)
    d = np.stack([x, y, -np.ones_like(x)], -1)
    return d / np.linalg.norm(d, axis=-1, keepdims=True)


def part_index(pass_index: np.ndarray, world_position: np.ndarray) -> np.ndarray:
    """Sub-samples' index into :data:`PARTS` from their object pass index ``(n, n)`` and
    world position ``(n, n, 3)``."""
    index = np.rint(pass_index).astype(np.int64)
    if index.min() < 0 or index.max() >= len(PARTS):
        raise ScreenGeometryError(f"pass indices {index.min()}..{index.max()} name no part")
    shell = index == PARTS.index("ball")
    inner = np.linalg.norm(world_position, axis=-1) < RING_RADIUS
    index[shell & inner] = PARTS.index("ring")
    return index


@dataclass(frozen=True)
class ScreenGeometry:
    """The per-pixel geometry buffers of one resolution (see the module docstring)."""

    position: np.ndarray
    normal: np.ndarray
    tangent: np.ndarray
    bitangent: np.ndarray
    parts: np.ndarray
    camera_to_world: tuple[tuple[float, ...], ...]
    camera_location: tuple[float, float, float]
    half_width: float
    occluders: dict = field(default_factory=occluders)
    materials: dict = field(default_factory=lambda: copy.deepcopy(SCENE_MATERIALS))

    def __post_init__(self) -> None:
        r = self.resolution
        for name in ARRAYS:
            a = getattr(self, name)
            want = (len(PARTS) if name == "parts" else 3, r, r)
            if a.shape != want or a.dtype != np.float32:
                raise ScreenGeometryError(f"{name} is {a.dtype} {a.shape}, not float32 {want}")

    @property
    def resolution(self) -> int:
        return self.position.shape[-1]

    def meta(self) -> dict:
        return {
            "camera_to_world": [list(map(float, row)) for row in self.camera_to_world],
            "camera_location": list(map(float, self.camera_location)),
            "half_width": float(self.half_width),
            "parts": list(PARTS),
            "occluders": self.occluders,
            "materials": self.materials,
        }

    def arrays(self) -> dict[str, np.ndarray]:
        return {name: getattr(self, name) for name in ARRAYS}

    @classmethod
    def from_arrays(cls, arrays: dict[str, np.ndarray], meta: dict) -> ScreenGeometry:
        if list(meta.get("parts", [])) != list(PARTS):
            raise ScreenGeometryError(f"parts {meta.get('parts')} are not {list(PARTS)}")
        return cls(
            **{name: np.asarray(arrays[name]) for name in ARRAYS},
            camera_to_world=tuple(tuple(row) for row in meta["camera_to_world"]),
            camera_location=tuple(meta["camera_location"]),
            half_width=meta["half_width"],
            occluders=meta["occluders"],
            materials=meta["materials"],
        )


def from_subsamples(
    world_position: np.ndarray,
    world_normal: np.ndarray,
    world_tangent: np.ndarray,
    world_bitangent: np.ndarray,
    pass_index: np.ndarray,
    supersample: int,
    taps: np.ndarray,
    camera: Camera = CAMERA,
) -> ScreenGeometry:
    """Per-pixel buffers from a supersampled render's world-space AOVs (``(n, n, 3)`` each,
    0 where nothing was hit; ``pass_index (n, n)``), filtered with ``taps``
    (:func:`render_jobs.pixel_filter.filter_taps`)."""
    rot = camera_to_world(camera)
    parts = part_index(pass_index, world_position)
    surface = (parts != PARTS.index("sky"))[..., None]
    material = np.isin(parts, [PARTS.index(p) for p in ("ball", "ring", "core")])[..., None]
    to_camera = (world_position - np.asarray(camera.location)) @ rot  # rows: x . rot
    channels = {
        "position": np.where(surface, to_camera, 0.0),
        "normal": np.where(surface, world_normal @ rot, 0.0),
        "tangent": np.where(material, world_tangent @ rot, 0.0),
        "bitangent": np.where(material, world_bitangent @ rot, 0.0),
    }
    onehot = (parts[None] == np.arange(len(PARTS))[:, None, None]).astype(np.float32)
    channels = {k: v.transpose(2, 0, 1) for k, v in channels.items()} | {"parts": onehot}
    # the window reaches past the frame's edge, where the render has no sub-samples: weigh
    # what it covers inside by that part's weight (Cycles sees the scene go on there)
    inside = filter_image(np.ones((1, *parts.shape), np.float32), supersample, taps)
    out = {k: filter_image(v, supersample, taps) / inside for k, v in channels.items()}
    return ScreenGeometry(
        **{k: np.ascontiguousarray(v, np.float32) for k, v in out.items()},
        camera_to_world=tuple(tuple(map(float, row)) for row in rot),
        camera_location=tuple(map(float, camera.location)),
        half_width=half_width(camera),
    )
