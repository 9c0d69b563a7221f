"""Ground truth: everything that describes and runs a shaderball render in Blender Cycles.

Layers (a render is plain data; one Blender backend turns it into a scene):

- plain data, importable anywhere, never imports ``bpy``:
  ``specs`` (frozen render specs), ``sun`` (sun sampling and the sun lamp's physics),
  ``materials`` (uniform / procedural / SVBRDF-file sources into validated maps),
  ``exr`` (multilayer EXR I/O), ``tonemap``, ``contact_sheet``, ``screen_uv`` (the ball's
  UV layout as the camera sees it, and Cycles' pixel filter);
- ``render_jobs.blender``: the only code that imports ``bpy``, and only inside a Blender
  worker process (``render_jobs.process`` starts one; the farm's Ray actors are others).

Importing ``render_jobs`` (or ``farm``, ``storage``, ``trainer``) never loads Blender.
"""

from render_jobs.errors import MaterialError, RenderError

__all__ = ["MaterialError", "RenderError"]
