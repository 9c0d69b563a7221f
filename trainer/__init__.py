"""The neural renderer's trainer: U-Net + light encoder, streaming DDP over shards (issue #5).

Not built yet: the ``trainer`` command group exists so the CLI surface is in place.
Importing ``trainer`` never loads Blender.
"""
