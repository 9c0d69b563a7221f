"""The paper's neural renderer: a U-Net over screen-space maps with a light encoder.

Knows nothing of data loading or distribution. Shapes (``H`` = ``W`` = ``resolution``,
divisible by 16; ``w`` = ``width``, 64 in the paper)::

    maps  (N, C, H, W) float in [0, 1]         C = 10 (diffuse 3, specular 3, roughness 1,
                                                normal 3), or 12 with roughness_channels=3
    light (N, 4) float                          sun direction (unit, z up) + turbidity / 10
    enc1..enc4: 3x3 stride-2 conv + BatchNorm + ReLU: w, 2w, 4w, 8w channels, H/2 .. H/16
    light encoder: Linear 4→32→128→256→(H/16)², each + Tanh; the (H/16)² values are one
        (H/16)x(H/16) plane replicated to 128 channels and concatenated at the bottleneck
    fuse: 3x3 conv (8w + 128 → 8w) + BN + ReLU at H/16
    decoder: at each level concat the skip (none in the no-skip ablation), 3x3 conv + BN + ReLU,
        bilinear x2 upsampling (as the authors' code; the paper says deconvolutions)
    out: 3x3 conv w → 3, Sigmoid → (N, 3, H, W) tonemapped image in [0, 1]

Glorot (Xavier) uniform initialisation for every conv and linear weight, zero biases.
"""

from __future__ import annotations

import copy
from dataclasses import asdict, dataclass

import torch
import torch.nn.functional as F
from torch import nn

from storage.schema import untrainable

LIGHT_CHANNELS = 128
#: the models: the paper's U-Net, and Zsolnai-Fehér et al. 2018's baseline (trainer.zf)
ARCHS = ("unet", "zf")


@dataclass(frozen=True)
class ModelConfig:
    resolution: int = 400
    width: int = 64  # channels of the first encoder level (the paper's 64)
    skips: bool = True  # False: the paper's no-skip-connection ablation
    roughness_channels: int = 1  # 3: roughness repeated, as the authors' 12-channel input
    arch: str = "unet"  # one of ARCHS

    def __post_init__(self) -> None:
        why = untrainable(self.resolution, nearest=False)
        if why:
            raise ValueError(why)
        if self.width < 1:
            raise ValueError(f"width must be positive, not {self.width}")
        if self.arch not in ARCHS:
            raise ValueError(f"arch must be one of {ARCHS}, not {self.arch!r}")
        if self.roughness_channels not in (1, 3):
            raise ValueError(f"roughness_channels must be 1 or 3, not {self.roughness_channels}")

    @property
    def in_channels(self) -> int:
        return 9 + self.roughness_channels

    @property
    def bottleneck(self) -> int:
        return self.resolution // 16

    def to_dict(self) -> dict:
        return asdict(self)


def check_inputs(cfg: ModelConfig, maps: torch.Tensor, light: torch.Tensor) -> None:
    """Raise ``ValueError`` naming the first input whose shape does not fit a model of
    ``cfg`` (every model takes the same ``(maps, light)`` batches)."""
    want = (cfg.in_channels, cfg.resolution, cfg.resolution)
    if maps.dim() != 4 or tuple(maps.shape[1:]) != want:
        raise ValueError(
            f"maps have shape {tuple(maps.shape)}, the model takes (N, {want[0]}, "
            f"{want[1]}, {want[2]}): {cfg.in_channels} channels at its {cfg.resolution}² "
            "resolution"
        )
    if light.dim() != 2 or light.shape != (maps.shape[0], 4):
        raise ValueError(f"light has shape {tuple(light.shape)}, expected ({maps.shape[0]}, 4)")


def glorot_init(model: nn.Module) -> None:
    """Glorot (Xavier) uniform weights and zero biases for every (transposed) convolution
    and linear layer of ``model``."""
    for m in model.modules():
        if isinstance(m, nn.Conv2d | nn.ConvTranspose2d | nn.Linear):
            nn.init.xavier_uniform_(m.weight)
            if m.bias is not None:
                nn.init.zeros_(m.bias)


def _block(cin: int, cout: int, stride: int = 1) -> nn.Sequential:
    return nn.Sequential(
        nn.Conv2d(cin, cout, 3, stride=stride, padding=1, bias=False),
        nn.BatchNorm2d(cout),
        nn.ReLU(inplace=True),
    )


class LightEncoder(nn.Module):
    """``(N, 4)`` → ``(N, 128, b, b)``: one Tanh-MLP plane, replicated along channels."""

    def __init__(self, bottleneck: int):
        super().__init__()
        self.b = bottleneck
        sizes = [4, 32, 128, 256, bottleneck * bottleneck]
        layers: list[nn.Module] = []
        for a, c in zip(sizes, sizes[1:], strict=False):
            layers += [nn.Linear(a, c), nn.Tanh()]
        self.mlp = nn.Sequential(*layers)

    def forward(self, light: torch.Tensor) -> torch.Tensor:
        plane = self.mlp(light).view(-1, 1, self.b, self.b)
        return plane.expand(-1, LIGHT_CHANNELS, -1, -1)


class NeuralRenderer(nn.Module):
    """The U-Net: ``forward(maps (N, C, H, W), light (N, 4)) → (N, 3, H, W)`` in [0, 1]."""

    def __init__(self, config: ModelConfig | None = None):
        super().__init__()
        self.config = cfg = config or ModelConfig()
        w = cfg.width
        chans = [w, 2 * w, 4 * w, 8 * w]
        self.encoder = nn.ModuleList(
            _block(a, c, stride=2) for a, c in zip([cfg.in_channels, *chans], chans, strict=False)
        )
        self.light = LightEncoder(cfg.bottleneck)
        self.fuse = _block(8 * w + LIGHT_CHANNELS, 8 * w)
        # decoder level i works at the resolution of encoder level i (deepest first)
        outs = [8 * w, 4 * w, 2 * w, w]
        ins = [8 * w, 8 * w, 4 * w, 2 * w]
        self.decoder = nn.ModuleList(
            _block(cin + (skip if cfg.skips else 0), cout)
            for cin, skip, cout in zip(ins, reversed(chans), outs, strict=True)
        )
        self.out = nn.Conv2d(w, 3, 3, padding=1)
        self.reset_parameters()

    def reset_parameters(self) -> None:
        glorot_init(self)

    def check_inputs(self, maps: torch.Tensor, light: torch.Tensor) -> None:
        check_inputs(self.config, maps, light)

    def forward(self, maps: torch.Tensor, light: torch.Tensor) -> torch.Tensor:
        skips = []
        x = maps
        for enc in self.encoder:
            x = enc(x)
            skips.append(x)
        x = self.fuse(torch.cat([x, self.light(light).to(x.dtype)], 1))
        for i, dec in enumerate(self.decoder):
            if self.config.skips:
                x = torch.cat([x, skips[-1 - i]], 1)
            x = F.interpolate(dec(x), scale_factor=2, mode="bilinear", align_corners=False)
        return torch.sigmoid(self.out(x))


def build_model(config: ModelConfig) -> nn.Module:
    """The model ``config.arch`` names (both take ``(maps, light)`` batches)."""
    if config.arch == "zf":
        from trainer.zf import ZsolnaiFeherRenderer

        return ZsolnaiFeherRenderer(config)
    return NeuralRenderer(config)


def count_parameters(model: nn.Module) -> int:
    return sum(p.numel() for p in model.parameters())


@torch.no_grad()
def fold_batchnorm(model: NeuralRenderer) -> NeuralRenderer:
    """An inference copy (eval mode) with each BatchNorm folded into the convolution before
    it, using the running statistics: the same outputs with fewer kernels and less traffic."""
    folded = copy.deepcopy(model).eval()
    for block in [*folded.encoder, folded.fuse, *folded.decoder]:
        conv, bn = block[0], block[1]
        scale = bn.weight / torch.sqrt(bn.running_var + bn.eps)
        conv.weight = nn.Parameter(conv.weight * scale[:, None, None, None])
        conv.bias = nn.Parameter(bn.bias - bn.running_mean * scale)
        block[1] = nn.Identity()
    return folded
