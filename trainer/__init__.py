"""The neural renderer's trainer: U-Net + light encoder, streaming DDP over shards.

``trainer launch`` / ``train`` / ``eval`` / ``render`` / ``viewer`` (``trainer.cli``); the
Python API is ``trainer.rendering.infer.Renderer``, and ``trainer.rendering.mapping`` turns any
material's maps into its input without Blender; ``trainer.rendering.viewer`` is the web viewer.
Importing ``trainer`` never loads Blender.
"""
