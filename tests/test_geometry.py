"""The shaderball's geometry, checked without Blender."""

import subprocess
import sys

import numpy as np

from render_jobs import geometry


def face_normals(mesh):
    out = []
    for f in mesh.faces:
        p = mesh.verts[list(f)]
        out.append(np.cross(p[1] - p[0], p[2] - p[0]))
    return np.array(out)


def centres(mesh):
    return np.array([mesh.verts[list(f)].mean(0) for f in mesh.faces])


def test_hash_is_stable_across_processes():
    code = "from render_jobs import geometry as g; print(g.geometry_hash(g.shaderball()))"
    runs = {
        subprocess.run(
            [sys.executable, "-c", code], capture_output=True, text=True, check=True
        ).stdout.strip()
        for _ in range(2)
    }
    assert runs == {geometry.geometry_hash(geometry.shaderball())}


def test_core_faces_point_outwards_and_uvs_cover_the_unit_square():
    core = geometry.shaderball()["core"]
    assert (np.einsum("ij,ij->i", face_normals(core), centres(core)) > 0).all()
    uv = np.array(core.uvs)
    assert len(uv) == sum(len(f) for f in core.faces)
    assert uv.min() == 0.0 and uv.max() == 1.0


def test_shell_has_a_band_and_an_inner_wall():
    shell = geometry.shell()
    radii = np.linalg.norm(shell.verts, axis=1)
    np.testing.assert_allclose(
        sorted({round(r, 6) for r in radii}), [1 - geometry.SHELL_THICKNESS, 1.0]
    )
    # un-tilt: no face centre lies inside the band
    tilt = np.radians(geometry.BAND_TILT_DEG)
    axis = np.array([np.sin(tilt), 0, np.cos(tilt)])
    outer = [
        c
        for c, f in zip(centres(shell), shell.faces, strict=True)
        if np.linalg.norm(shell.verts[list(f)], axis=1).min() > 0.999
    ]
    assert min(abs(np.asarray(outer) @ axis)) >= geometry.BAND_HALF_WIDTH * 0.99
    # outer faces point out, inner faces point in (towards the core)
    n = face_normals(shell)
    radial = np.einsum("ij,ij->i", n, centres(shell))
    r = np.linalg.norm(centres(shell), axis=1)
    assert (radial[r > 0.99] > 0).all() and (radial[r < 0.95] < 0).all()


def test_uv_seam_faces_away_from_the_camera():
    core = geometry.shaderball()["core"]
    front = [i for i, c in enumerate(centres(core)) if c[1] < -0.8]  # faces seen by the camera
    corner = 0
    starts = []
    for f in core.faces:
        starts.append(corner)
        corner += len(f)
    us = [core.uvs[starts[i]][0] for i in front]
    assert min(us) > 0.25 and max(us) < 0.75
