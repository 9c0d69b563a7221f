"""The baseline of the paper's Table 1: Zsolnai-Fehér et al. 2018's direct neural renderer
(Gaussian Material Synthesis, SIGGRAPH 2018): a material's parameter vector to an image of
the fixed scene, with no light input and no screen-space maps.

Their exact layer list is not reproduced in the seed paper, which says only that the network
is fully connected layers followed by up-convolutions with about 10x its own parameters. The
architecture assumed here, at ``H`` = ``resolution`` (divisible by 16), ``b`` = ``H / 16``::

    params (N, 10)                 the material's values: the masked mean of each map channel
                                   (diffuse 3, specular 3, roughness 1, normal 3); for the
                                   uniform materials it is trained on, exactly their values
    fc: Linear 10→512→1024→1024, each + ReLU; Linear 1024 → 256·b², ReLU
    up: 4 x [ConvTranspose2d 4x4 stride 2 + BatchNorm + ReLU]: 256 → 128 → 64 → 32 → 16
    out: 3x3 conv 16 → 3, Sigmoid → (N, 3, H, W) tonemapped image in [0, 1]

At 400² that is 166 M parameters, 14x the U-Net's 11.7 M (the last fully connected layer is
most of it); at 128², 19.1 M (1.6x). It takes the same ``(maps, light)`` batch as
:class:`trainer.model.NeuralRenderer`, so it trains, saves and evaluates through the same
code, and it ignores ``light``: it can only learn one lighting, so it is trained and compared
on a fixed-sun store (``farm submit --fixed-sun``).
"""

from __future__ import annotations

import torch
from torch import nn

from trainer.model import ModelConfig, check_inputs, glorot_init

FC = (512, 1024, 1024)
UP = (256, 128, 64, 32, 16)


def material_vector(maps: torch.Tensor) -> torch.Tensor:
    """``(N, C, H, W)`` maps → ``(N, C)``: each channel's mean over the ball (the pixels
    whose normal map is set: its z channel is above 0.25; the background's maps are 0)."""
    mask = (maps[:, -1:] > 0.25).to(maps.dtype)
    return (maps * mask).sum((2, 3)) / mask.sum((2, 3)).clamp_min(1.0)


class ZsolnaiFeherRenderer(nn.Module):
    """``forward(maps (N, C, H, W), light (N, 4)) → (N, 3, H, W)``; ``light`` is ignored."""

    def __init__(self, config: ModelConfig):
        super().__init__()
        self.config = cfg = config
        self.b = cfg.resolution // 16
        sizes = [cfg.in_channels, *FC]
        layers: list[nn.Module] = []
        for a, c in zip(sizes, sizes[1:], strict=False):
            layers += [nn.Linear(a, c), nn.ReLU(inplace=True)]
        layers += [nn.Linear(FC[-1], UP[0] * self.b * self.b), nn.ReLU(inplace=True)]
        self.fc = nn.Sequential(*layers)
        ups: list[nn.Module] = []
        for a, c in zip(UP, UP[1:], strict=False):
            ups += [
                nn.ConvTranspose2d(a, c, 4, stride=2, padding=1, bias=False),
                nn.BatchNorm2d(c),
                nn.ReLU(inplace=True),
            ]
        self.up = nn.Sequential(*ups)
        self.out = nn.Conv2d(UP[-1], 3, 3, padding=1)
        glorot_init(self)

    def check_inputs(self, maps: torch.Tensor, light: torch.Tensor) -> None:
        check_inputs(self.config, maps, light)

    def forward(self, maps: torch.Tensor, light: torch.Tensor) -> torch.Tensor:
        x = self.fc(material_vector(maps)).view(-1, UP[0], self.b, self.b)
        return torch.sigmoid(self.out(self.up(x)))
