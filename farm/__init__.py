"""The render farm: plans materials x suns into render jobs and runs them on Blender workers.

So far: ``farm preview`` (one material, rendered locally in a Blender worker process).
The Ray farm (``farm submit``, ``farm status``, the dashboard) builds on it (issue #4).
Importing ``farm`` never loads Blender.
"""
