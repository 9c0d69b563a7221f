"""The networks by name (``ModelConfig.arch``): the paper's U-Net and Zsolnai-Fehér et al.
2018's baseline, both taking ``(maps, light)`` batches."""

from __future__ import annotations

from torch import nn

from render_jobs.screen_geometry import ScreenGeometry
from trainer.model import ModelConfig, NeuralRenderer
from trainer.zf import ZsolnaiFeherRenderer


def build_model(config: ModelConfig, geometry: ScreenGeometry | None = None) -> nn.Module:
    """The model ``config.arch`` names (both take ``(maps, light)`` batches), its scene
    buffers from ``geometry`` when it has cues."""
    if config.arch == "zf":
        return ZsolnaiFeherRenderer(config)
    return NeuralRenderer(config, geometry)
