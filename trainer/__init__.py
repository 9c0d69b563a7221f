"""The neural renderer's trainer: U-Net + light encoder, streaming DDP over shards.

``trainer launch`` / ``train`` / ``eval`` / ``render`` / ``viewer`` (``trainer.cli``); the
Python API is ``trainer.infer.Renderer``, and ``trainer.mapping`` turns any material's maps
into its input without Blender; ``trainer.viewer`` is the web viewer. Importing ``trainer``
never loads Blender.
"""
