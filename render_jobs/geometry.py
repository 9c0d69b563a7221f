"""The shaderball's geometry as plain arrays, built analytically in numpy (no ``bpy``).

Built in code rather than with bmesh operators because those order (and so round) their
results differently from run to run; numpy gives the same bits on every worker and run.

- ``shell``: a UV sphere (radius 1, 128 x 64) with a band of latitude rows removed
  (|z| < 0.12 at row centres), made solid: an inner surface 0.05 inside and rim faces along
  both cut edges; then tilted 25° about the camera's view axis (Y).
- ``core``: a UV sphere (radius 0.86, 96 x 48) that the band reveals.
- ``pedestal``: a tapered column from the ball down to a base disc; ``ground``: a 40 m plane.

UVs are equirectangular: u runs around (u = 0 at +Y, the back, so the seam faces away from the
camera at -Y; the front is u = 0.5), v runs from 0 (south pole) to 1 (north pole).
Faces wind counter-clockwise seen from outside.
"""

from __future__ import annotations

import hashlib
import math
from dataclasses import dataclass, field

import numpy as np

from render_jobs.specs import CAMERA, Camera

BALL_RADIUS = 1.0
SHELL_THICKNESS = 0.05
CORE_RADIUS = 0.86
BAND_HALF_WIDTH = 0.12
BAND_TILT_DEG = 25.0
GROUND_Z = -1.5
MATERIAL_OBJECTS = ("shell", "core")


@dataclass
class Mesh:
    """``verts`` (N, 3) float64; ``faces`` lists of vertex indices; ``uvs`` one (u, v) per
    face corner, in face order (empty when the mesh has no UVs); ``smooth`` shading flag."""

    verts: np.ndarray
    faces: list[tuple[int, ...]]
    uvs: list[tuple[float, float]] = field(default_factory=list)
    smooth: bool = True


def _sphere_parts(radius: float, u: int, v: int):
    """Vertices, and faces with UVs per row, of a UV sphere. Row r lies between ring r and
    r + 1, ring 0 being the north pole and ring v the south pole."""
    phi = math.pi / 2 + 2 * math.pi * np.arange(u) / u  # u = 0 at +Y
    theta = math.pi * np.arange(1, v) / v
    st, ct = np.sin(theta)[:, None], np.cos(theta)[:, None]
    rings = np.stack(
        [st * np.cos(phi)[None], st * np.sin(phi)[None], np.broadcast_to(ct, (v - 1, u))], -1
    )
    verts = np.concatenate([[[0, 0, 1]], rings.reshape(-1, 3), [[0, 0, -1]]]) * radius
    south = len(verts) - 1

    def ring(r: int, i: int) -> int:
        return 1 + (r - 1) * u + (i % u)

    rows = []
    for r in range(v):
        faces, uvs = [], []
        v0, v1 = 1 - r / v, 1 - (r + 1) / v
        for i in range(u):
            u0, u1 = i / u, (i + 1) / u
            if r == 0:
                faces.append((0, ring(1, i), ring(1, i + 1)))
                uvs += [((i + 0.5) / u, 1.0), (u0, v1), (u1, v1)]
            elif r == v - 1:
                faces.append((south, ring(r, i + 1), ring(r, i)))
                uvs += [((i + 0.5) / u, 0.0), (u1, v0), (u0, v0)]
            else:
                faces.append((ring(r, i), ring(r + 1, i), ring(r + 1, i + 1), ring(r, i + 1)))
                uvs += [(u0, v0), (u0, v1), (u1, v1), (u1, v0)]
        rows.append((faces, uvs))
    return verts, rows, ring


def uv_sphere(radius: float, u: int, v: int) -> Mesh:
    verts, rows, _ = _sphere_parts(radius, u, v)
    return Mesh(verts, [f for faces, _ in rows for f in faces], [c for _, uvs in rows for c in uvs])


def _rotation_y(deg: float) -> np.ndarray:
    c, s = math.cos(math.radians(deg)), math.sin(math.radians(deg))
    return np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]])


def shell(u: int = 128, v: int = 64) -> Mesh:
    """The outer shell: sphere minus a latitude band, solid, tilted."""
    outer, rows, ring = _sphere_parts(BALL_RADIUS, u, v)
    mid_z = [math.cos(math.pi * (r + 0.5) / v) for r in range(v)]
    keep = [r for r in range(v) if abs(mid_z[r]) >= BAND_HALF_WIDTH]
    cut = [r for r in range(v) if r not in keep]
    top_edge, bottom_edge = cut[0], cut[-1] + 1  # boundary rings of the two caps
    n = len(outer)
    inner = outer * ((BALL_RADIUS - SHELL_THICKNESS) / BALL_RADIUS)
    faces, uvs = [], []
    for r in keep:
        row_faces, row_uvs = rows[r]
        faces += row_faces
        uvs += row_uvs
        k = len(row_faces[0])
        for j, f in enumerate(row_faces):  # inner surface, reversed winding
            faces.append(tuple(n + i for i in reversed(f)))
            uvs += list(reversed(row_uvs[j * k : (j + 1) * k]))
    verts = np.concatenate([outer, inner])
    for edge, facing in ((top_edge, -1.0), (bottom_edge, 1.0)):
        vv = 1 - edge / v
        for i in range(u):
            a, b = ring(edge, i), ring(edge, i + 1)
            quad = (a, b, n + b, n + a)
            p = verts[list(quad)]
            normal = np.cross(p[1] - p[0], p[3] - p[0])
            if normal[2] * facing < 0:
                quad = tuple(reversed(quad))
            faces.append(quad)
            uvs += [(i / u, vv), ((i + 1) / u, vv), ((i + 1) / u, vv - 0.01), (i / u, vv - 0.01)]
            if normal[2] * facing < 0:
                uvs[-4:] = list(reversed(uvs[-4:]))
    verts = verts @ _rotation_y(BAND_TILT_DEG).T
    return Mesh(verts, faces, uvs)


def frustum(z0: float, z1: float, r0: float, r1: float, segments: int = 64) -> Mesh:
    """A closed tapered cylinder from z0 (radius r0) up to z1 (radius r1), capped by fans."""
    phi = 2 * math.pi * np.arange(segments) / segments
    circle = np.stack([np.cos(phi), np.sin(phi), np.zeros_like(phi)], -1)
    bottom, top = circle * [r0, r0, 0] + [0, 0, z0], circle * [r1, r1, 0] + [0, 0, z1]
    verts = np.concatenate([bottom, top, [[0, 0, z0], [0, 0, z1]]])
    cb, ct = 2 * segments, 2 * segments + 1
    faces = []
    for i in range(segments):
        j = (i + 1) % segments
        faces.append((i, j, segments + j, segments + i))
        faces.append((cb, j, i))
        faces.append((ct, segments + i, segments + j))
    return Mesh(verts, faces, smooth=False)


def pedestal() -> Mesh:
    column, base = (frustum(**f) for f in occluders()["frustums"])
    offset = len(column.verts)
    faces = column.faces + [tuple(i + offset for i in f) for f in base.faces]
    return Mesh(np.concatenate([column.verts, base.verts]), faces, smooth=False)


def ground(size: float = 40.0) -> Mesh:
    h = size / 2
    verts = np.array([[-h, -h, GROUND_Z], [h, -h, GROUND_Z], [h, h, GROUND_Z], [-h, h, GROUND_Z]])
    return Mesh(verts, [(0, 1, 2, 3)], smooth=False)


def shaderball() -> dict[str, Mesh]:
    """Every mesh of the scene, by object name."""
    return {
        "shell": shell(),
        "core": uv_sphere(CORE_RADIUS, 96, 48),
        "pedestal": pedestal(),
        "ground": ground(),
    }


def band_limits(v: int = 64) -> tuple[float, float]:
    """The shell's cut as heights on the untilted unit sphere: the rings that bound it."""
    mid_z = [math.cos(math.pi * (r + 0.5) / v) for r in range(v)]
    cut = [r for r in range(v) if abs(mid_z[r]) < BAND_HALF_WIDTH]
    return math.cos(math.pi * (cut[-1] + 1) / v), math.cos(math.pi * cut[0] / v)


def occluders() -> dict:
    """The scene's shadow casters as analytic shapes (JSON-safe), for a sun-visibility test
    without Blender: spheres (``centre``, ``radius``, and the ``band`` of heights along
    ``axis``, as fractions of the radius, where a sphere is cut open: the shell's outer and
    inner faces, then the core) and vertical frustums (``z0``, ``z1``, ``r0``, ``r1``: the
    stand's column and base). The floor casts no shadow on anything the camera sees."""
    axis = _rotation_y(BAND_TILT_DEG) @ np.array([0.0, 0.0, 1.0])
    lo, hi = band_limits()
    band = {"axis": [float(a) for a in axis], "lo": lo, "hi": hi}
    top = -BALL_RADIUS * 0.9
    return {
        "spheres": [
            {"centre": [0.0, 0.0, 0.0], "radius": BALL_RADIUS, **band},
            {"centre": [0.0, 0.0, 0.0], "radius": BALL_RADIUS - SHELL_THICKNESS, **band},
            {
                "centre": [0.0, 0.0, 0.0],
                "radius": CORE_RADIUS,
                "axis": [0.0, 0.0, 1.0],
                "lo": 0.0,
                "hi": 0.0,
            },
        ],  # fmt: skip
        "frustums": [
            {"z0": GROUND_Z + 0.1, "z1": top, "r0": 0.30, "r1": 0.24},
            {"z0": GROUND_Z, "z1": GROUND_Z + 0.1, "r0": 0.62, "r1": 0.58},
        ],
    }


def geometry_hash(meshes: dict[str, Mesh], camera: Camera = CAMERA) -> str:
    """SHA-256 of every mesh (float32 vertices, faces, float32 UVs) and the camera spec."""
    h = hashlib.sha256()
    for name in sorted(meshes):
        m = meshes[name]
        h.update(name.encode())
        h.update(np.asarray(m.verts, np.float32).tobytes())
        for f in m.faces:
            h.update(np.asarray((len(f),) + tuple(f), np.int32).tobytes())
        h.update(np.asarray(m.uvs, np.float32).tobytes())
    h.update(repr(sorted(camera.to_dict().items())).encode())
    return h.hexdigest()
