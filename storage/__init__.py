"""The shard store: sharded zarr v3 stores of screen-space maps and renders (issue #3).

Not built yet: the ``shards`` command group exists so the CLI surface is in place, and has no
commands until the store does. Importing ``storage`` never loads Blender.
"""
