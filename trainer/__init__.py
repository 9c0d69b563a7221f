"""The neural renderer's trainer: U-Net + light encoder, streaming DDP over shards.

``trainer launch`` / ``train`` / ``eval`` / ``render`` (``trainer.cli``); the Python API is
``trainer.infer.Renderer``. Importing ``trainer`` never loads Blender.
"""
