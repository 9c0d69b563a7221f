"""The fixed shaderball scene: geometry built in code, deterministic, plus the camera.

- Outer shell: a UV sphere (radius 1, 128 x 64 segments), its material-carrying surface cut by a
  band 0.26 wide tilted 25° about the view axis, made solid (0.05 thick) so the cut shows
  edges; inside it, a core sphere (radius 0.86) that the band reveals. Both carry the SVBRDF.
- A pedestal (column and base disc) and a ground plane, with fixed neutral materials, so
  that self-shadowing and inter-reflection show.
- UVs: equirectangular (u around, v pole to pole); the seam is turned away from the camera.
- The camera (``render_jobs.specs.CAMERA``) looks at the ball from -Y.

``geometry_hash()`` hashes every mesh's vertices, faces and UVs and the camera, so that
workers can prove they render the same scene.
"""

from __future__ import annotations

import hashlib
import math

import numpy as np

from render_jobs.blender.bpy_guard import bmesh, bpy, mathutils
from render_jobs.specs import CAMERA, Camera

BALL_RADIUS = 1.0
SHELL_THICKNESS = 0.05
CORE_RADIUS = 0.86
BAND_HALF_WIDTH = 0.12
BAND_TILT_DEG = 25.0
GROUND_Z = -1.5
MATERIAL_OBJECTS = ("shell", "core")


def _sphere(bm, radius: float, u: int, v: int) -> None:
    if not bm.loops.layers.uv:
        bm.loops.layers.uv.new("UVMap")  # calc_uvs fills the active layer; it must exist
    bmesh.ops.create_uvsphere(bm, u_segments=u, v_segments=v, radius=radius, calc_uvs=True)
    # turn the UV seam (at +X in bmesh's layout) to the back, away from the camera at -Y
    bmesh.ops.rotate(
        bm, verts=bm.verts, cent=(0, 0, 0), matrix=mathutils.Matrix.Rotation(math.pi / 2, 3, "Z")
    )
    for f in bm.faces:
        f.smooth = True


def _shell(bm) -> None:
    _sphere(bm, BALL_RADIUS, 128, 64)
    # cut along latitude rings (clean edges), then tilt the shell about the view axis
    cut = [f for f in bm.faces if abs(f.calc_center_median().z) < BAND_HALF_WIDTH]
    bmesh.ops.delete(bm, geom=cut, context="FACES")
    bmesh.ops.solidify(bm, geom=list(bm.faces), thickness=SHELL_THICKNESS)
    tilt = mathutils.Matrix.Rotation(math.radians(BAND_TILT_DEG), 3, "Y")
    bmesh.ops.rotate(bm, verts=bm.verts, cent=(0, 0, 0), matrix=tilt)


def _core(bm) -> None:
    _sphere(bm, CORE_RADIUS, 96, 48)


def _pedestal(bm) -> None:
    top = -BALL_RADIUS * 0.9
    column = bmesh.ops.create_cone(
        bm, cap_ends=True, segments=64, radius1=0.30, radius2=0.24, depth=top - GROUND_Z
    )
    bmesh.ops.translate(bm, verts=column["verts"], vec=(0, 0, (top + GROUND_Z) / 2))
    base = bmesh.ops.create_cone(
        bm, cap_ends=True, segments=64, radius1=0.62, radius2=0.58, depth=0.1
    )
    bmesh.ops.translate(bm, verts=base["verts"], vec=(0, 0, GROUND_Z + 0.05))


def _ground(bm) -> None:
    grid = bmesh.ops.create_grid(bm, x_segments=1, y_segments=1, size=40.0)
    bmesh.ops.translate(bm, verts=grid["verts"], vec=(0, 0, GROUND_Z))


_BUILDERS = {"shell": _shell, "core": _core, "pedestal": _pedestal, "ground": _ground}


def _canonical_mesh(bm, name: str):
    """A mesh with ``bm``'s geometry in a canonical element order.

    bmesh's primitive builders order faces and loops differently from run to run; the order
    changes quad triangulation and the BVH, hence the noise of a render. Vertices are sorted
    by position, each face starts at its smallest vertex, faces are sorted.
    """
    uv_layer = bm.loops.layers.uv.active
    keys = [tuple(round(c, 6) for c in v.co) for v in bm.verts]
    order = sorted(range(len(keys)), key=keys.__getitem__)
    if len({keys[i] for i in order}) != len(keys):
        raise RuntimeError(f"{name}: coincident vertices make the mesh order ambiguous")
    new_index = {old: new for new, old in enumerate(order)}
    faces = []
    for f in bm.faces:
        loops = [(new_index[loop.vert.index], loop) for loop in f.loops]
        start = min(range(len(loops)), key=lambda i: loops[i][0])
        loops = loops[start:] + loops[:start]
        uvs = [tuple(loop[uv_layer].uv) if uv_layer else (0.0, 0.0) for _, loop in loops]
        faces.append(([i for i, _ in loops], uvs, f.smooth))
    faces.sort(key=lambda face: face[0])
    mesh = bpy.data.meshes.new(name)
    mesh.from_pydata([tuple(bm.verts[i].co) for i in order], [], [f[0] for f in faces])
    mesh.polygons.foreach_set("use_smooth", [f[2] for f in faces])
    if uv_layer:
        uv = mesh.uv_layers.new(name="UVMap")
        uv.data.foreach_set("uv", [c for f in faces for xy in f[1] for c in xy])
    mesh.update()
    return mesh


def build_geometry(scene) -> dict[str, object]:
    """Create the shaderball's objects in ``scene``; returns them by name."""
    objects = {}
    for name, build in _BUILDERS.items():
        bm = bmesh.new()
        build(bm)
        bm.verts.index_update()
        bm.verts.ensure_lookup_table()
        mesh = _canonical_mesh(bm, name)
        bm.free()
        obj = bpy.data.objects.new(name, mesh)
        scene.collection.objects.link(obj)
        objects[name] = obj
    return objects


def build_camera(scene, camera: Camera = CAMERA):
    """The fixed camera, made the scene's active camera."""
    data = bpy.data.cameras.new("camera")
    data.lens = camera.lens_mm
    data.sensor_width = camera.sensor_mm
    data.sensor_fit = "HORIZONTAL"
    obj = bpy.data.objects.new("camera", data)
    obj.location = camera.location
    forward = mathutils.Vector(camera.look_at) - mathutils.Vector(camera.location)
    obj.rotation_euler = forward.to_track_quat("-Z", "Y").to_euler()
    scene.collection.objects.link(obj)
    scene.camera = obj
    return obj


def geometry_hash(objects: dict[str, object], camera_obj) -> str:
    """SHA-256 of every mesh (vertices to 1e-5, faces, UVs) and the camera matrix."""
    h = hashlib.sha256()
    for name in sorted(objects):
        mesh = objects[name].data
        co = np.empty(len(mesh.vertices) * 3, np.float32)
        mesh.vertices.foreach_get("co", co)
        loops = np.empty(len(mesh.loops), np.int32)
        mesh.loops.foreach_get("vertex_index", loops)
        h.update(name.encode())
        h.update(np.round(co, 5).astype(np.float32).tobytes())
        h.update(loops.tobytes())
        if mesh.uv_layers:
            uv = np.empty(len(mesh.loops) * 2, np.float32)
            mesh.uv_layers[0].data.foreach_get("uv", uv)
            h.update(np.round(uv, 5).astype(np.float32).tobytes())
    m = np.array(camera_obj.matrix_basis, dtype=np.float32)
    h.update(np.round(m, 5).tobytes())
    h.update(np.float32(camera_obj.data.lens).tobytes())
    return h.hexdigest()
