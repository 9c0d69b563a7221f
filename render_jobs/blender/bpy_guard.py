"""The one import of ``bpy`` (and its companions ``bmesh``, ``mathutils``).

Every module of the backend imports Blender from here, so that one place says what loading
Blender means: refuse in a process that did not ask to be a Blender worker (the farm driver,
the trainer and the storage tools must never pay for it), and quiet Blender's stdout chatter.
Set ``SHADERBALL_BLENDER_WORKER=1`` (``render_jobs.process`` does) to allow the import.
"""

from __future__ import annotations

import os

WORKER_ENV = "SHADERBALL_BLENDER_WORKER"

if os.environ.get(WORKER_ENV) != "1":
    raise ImportError(
        "render_jobs.blender may only be imported in a Blender worker process "
        f"(set {WORKER_ENV}=1, or use render_jobs.process.RenderProcess)"
    )

# isort: off
import bpy  # noqa: E402  (first: bmesh and mathutils exist only once bpy is loaded)
import bmesh  # noqa: E402
import mathutils  # noqa: E402

# isort: on

__all__ = ["bpy", "bmesh", "mathutils"]
