"""The fixed shaderball scene in Blender: objects from ``render_jobs.geometry``, the camera.

``mesh_hash()`` hashes the meshes as Blender holds them (vertices, face corners, UVs), so a
worker proves the scene it renders is the same as every other worker's.
"""

from __future__ import annotations

import hashlib

import numpy as np

from render_jobs.blender.bpy_guard import bpy, mathutils
from render_jobs.geometry import Mesh, shaderball
from render_jobs.specs import CAMERA, Camera


def _to_blender(name: str, m: Mesh):
    mesh = bpy.data.meshes.new(name)
    mesh.from_pydata([tuple(v) for v in m.verts.tolist()], [], [list(f) for f in m.faces])
    mesh.polygons.foreach_set("use_smooth", [m.smooth] * len(m.faces))
    if m.uvs:
        layer = mesh.uv_layers.new(name="UVMap")
        layer.data.foreach_set("uv", np.asarray(m.uvs, np.float32).ravel())
    mesh.update()
    return mesh


def build_geometry(scene) -> dict[str, object]:
    """Create the shaderball's objects in ``scene``; returns them by name."""
    objects = {}
    for name, m in shaderball().items():
        obj = bpy.data.objects.new(name, _to_blender(name, m))
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


def mesh_hash(objects: dict[str, object], camera_obj) -> str:
    """SHA-256 of the Blender meshes (vertices, face corners, UVs) and the camera transform."""
    h = hashlib.sha256()
    for name in sorted(objects):
        mesh = objects[name].data
        co = np.empty(len(mesh.vertices) * 3, np.float32)
        mesh.vertices.foreach_get("co", co)
        loops = np.empty(len(mesh.loops), np.int32)
        mesh.loops.foreach_get("vertex_index", loops)
        h.update(name.encode() + co.tobytes() + loops.tobytes())
        if mesh.uv_layers:
            uv = np.empty(len(mesh.loops) * 2, np.float32)
            mesh.uv_layers[0].data.foreach_get("uv", uv)
            h.update(uv.tobytes())
    h.update(np.array(camera_obj.matrix_basis, dtype=np.float32).tobytes())
    h.update(np.float32(camera_obj.data.lens).tobytes())
    return h.hexdigest()
