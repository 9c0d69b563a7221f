"""The Blender backend: the only code in shaderball that imports ``bpy``.

Import it only inside a Blender worker process (``render_jobs.process`` or a farm actor):
``bpy`` is a whole Blender in the process (about 400 MB resident), and its module deadlocks in
a C++ static destructor at interpreter exit, so a process that imported it must leave with
``os._exit`` (``render_jobs.process`` does).
"""
