"""The neural renderer's trainer: U-Net + light encoder, streaming DDP over shards (issue #5).

``trainer launch`` / ``train`` / ``eval`` / ``render`` (``trainer.cli``); the Python API is
``trainer.infer.Renderer``. Importing ``trainer`` never loads Blender.
"""
