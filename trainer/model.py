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

Beyond the paper (each off in the paper's network, ``ModelConfig()``'s defaults):

- ``inputs``: scene cues concatenated after the maps (:mod:`trainer.scene`: the scene's
  geometry, the light as planes, shading normal, reflection, sun visibility, analytic
  shading), computed inside the network from constant buffers, so every caller still
  passes ``(maps, light)``;
- ``norm``: ``group`` (GroupNorm, per-sample statistics) instead of BatchNorm;
- ``head``: a full-resolution block over the last decoder level and the network's inputs
  before the output convolution (the paper's last level works at half resolution);
- ``residual``: the output is the ``shade`` cue corrected: ``sigmoid(out + logit(shade))``;
- ``decoder_convs``: more 3x3 conv + norm + ReLU blocks at each decoder level, after the one
  that takes the skip (the paper's one), before the upsampling: depth where the channels are
  few, for less time a step than more width (it learnt no more per image pass:
  docs/training.md).
"""

from __future__ import annotations

import copy
from dataclasses import asdict, dataclass

import torch
import torch.nn.functional as F
from torch import nn

from render_jobs.screen_geometry import ScreenGeometry
from render_jobs.tonemap import DEFAULT_EXPOSURE
from storage.schema import untrainable
from trainer.cues import NEEDS_GEOMETRY, check_cues, cue_channels, ordered
from trainer.scene import SceneInputs

LIGHT_CHANNELS = 128
#: the models: the paper's U-Net, and Zsolnai-Fehér et al. 2018's baseline (trainer.zf)
ARCHS = ("unet", "zf")
NORMS = ("batch", "group")
#: GroupNorm's groups (Wu & He 2018's default; every level's channels are a multiple of it
#: when the width is)
GROUPS = 8


@dataclass(frozen=True)
class ModelConfig:
    resolution: int = 400
    width: int = 64  # channels of the first encoder level (the paper's 64)
    skips: bool = True  # False: the paper's no-skip-connection ablation
    roughness_channels: int = 1  # 3: roughness repeated, as the authors' 12-channel input
    arch: str = "unet"  # one of ARCHS
    inputs: tuple[str, ...] = ()  # scene cues after the maps (trainer.scene.CUES)
    norm: str = "batch"  # one of NORMS
    head: bool = False  # a full-resolution block before the output convolution
    residual: bool = False  # correct the shade cue instead of drawing the image
    decoder_convs: int = 1  # 3x3 conv blocks at each decoder level (the paper's 1)
    exposure: float = DEFAULT_EXPOSURE  # the targets' tonemap, for the shade cue

    def __post_init__(self) -> None:
        check_cues(tuple(self.inputs))
        object.__setattr__(self, "inputs", ordered(self.inputs))
        why = untrainable(self.resolution, nearest=False)
        if why:
            raise ValueError(why)
        if self.width < 1:
            raise ValueError(f"width must be positive, not {self.width}")
        if self.decoder_convs < 1:
            raise ValueError(f"decoder_convs must be at least 1, not {self.decoder_convs}")
        if self.arch not in ARCHS:
            raise ValueError(f"arch must be one of {ARCHS}, not {self.arch!r}")
        if self.roughness_channels not in (1, 3):
            raise ValueError(f"roughness_channels must be 1 or 3, not {self.roughness_channels}")
        if self.norm not in NORMS:
            raise ValueError(f"norm must be one of {NORMS}, not {self.norm!r}")
        if self.norm == "group" and self.width % GROUPS:
            raise ValueError(f"GroupNorm needs a width that is a multiple of {GROUPS}")
        if self.residual and "shade" not in self.inputs:
            raise ValueError("a residual network corrects the shade cue: add it to the inputs")
        if self.arch == "zf" and not self.plain:
            raise ValueError("the Zsolnai-Fehér baseline takes the paper's inputs only")

    @property
    def in_channels(self) -> int:
        """The maps' channels, what every caller passes (``trainer.targets.model_inputs``)."""
        return 9 + self.roughness_channels

    @property
    def network_channels(self) -> int:
        """The channels the first convolution sees: the maps and the scene cues."""
        return self.in_channels + cue_channels(self.inputs)

    @property
    def needs_geometry(self) -> bool:
        """Whether the network needs the scene's geometry buffers."""
        return any(c in NEEDS_GEOMETRY for c in self.inputs)

    @property
    def plain(self) -> bool:
        """The paper's network: no cues, BatchNorm, no head, no residual, one conv a decoder
        level (the form the fast inference rewrites of ``trainer.rendering.fastnet`` take)."""
        return (
            not self.inputs and self.norm == "batch" and not self.head and not self.residual
            and self.decoder_convs == 1
        )  # fmt: skip

    @property
    def bottleneck(self) -> int:
        return self.resolution // 16

    def to_dict(self) -> dict:
        d = asdict(self)
        d["inputs"] = list(self.inputs)
        return d


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


def _block(cin: int, cout: int, stride: int = 1, norm: str = "batch") -> nn.Sequential:
    layer = nn.BatchNorm2d(cout) if norm == "batch" else nn.GroupNorm(GROUPS, cout)
    return nn.Sequential(
        nn.Conv2d(cin, cout, 3, stride=stride, padding=1, bias=False),
        layer,
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
    """The U-Net: ``forward(maps (N, C, H, W), light (N, 4)) → (N, 3, H, W)`` in [0, 1].

    ``geometry`` fills the scene cues' constant buffers (a network with cues that needs
    them and gets none has zeros there until a checkpoint's weights are loaded)."""

    def __init__(self, config: ModelConfig | None = None, geometry: ScreenGeometry | None = None):
        super().__init__()
        self.config = cfg = config or ModelConfig()
        w, norm = cfg.width, cfg.norm
        self.scene = None
        if cfg.inputs:
            self.scene = SceneInputs(
                cfg.inputs, cfg.resolution, cfg.roughness_channels, cfg.exposure, geometry
            )
        chans = [w, 2 * w, 4 * w, 8 * w]
        firsts = [cfg.network_channels, *chans]
        self.encoder = nn.ModuleList(
            _block(a, c, stride=2, norm=norm) for a, c in zip(firsts, chans, strict=False)
        )
        self.light = LightEncoder(cfg.bottleneck)
        self.fuse = _block(8 * w + LIGHT_CHANNELS, 8 * w, norm=norm)
        # decoder level i works at the resolution of encoder level i (deepest first)
        outs = [8 * w, 4 * w, 2 * w, w]
        ins = [8 * w, 8 * w, 4 * w, 2 * w]
        self.decoder = nn.ModuleList(
            _block(cin + (skip if cfg.skips else 0), cout, norm=norm)
            for cin, skip, cout in zip(ins, reversed(chans), outs, strict=True)
        )
        # absent in the paper's form, so its checkpoints keep their keys
        self.refine = None
        if cfg.decoder_convs > 1:
            self.refine = nn.ModuleList(
                nn.Sequential(*(_block(c, c, norm=norm) for _ in range(cfg.decoder_convs - 1)))
                for c in outs
            )
        self.head = _block(w + cfg.network_channels, w, norm=norm) if cfg.head else None
        self.out = nn.Conv2d(w, 3, 3, padding=1)
        self.reset_parameters()

    def reset_parameters(self) -> None:
        glorot_init(self)

    def check_inputs(self, maps: torch.Tensor, light: torch.Tensor) -> None:
        check_inputs(self.config, maps, light)

    def forward(
        self, maps: torch.Tensor, light: torch.Tensor, cues: torch.Tensor | None = None
    ) -> torch.Tensor:
        """The image of ``maps`` under ``light``; ``cues``: what the scene makes of them, made
        before (``trainer train --preload`` keeps each sample's), instead of making it here."""
        skips = []
        if self.scene is None:
            cues = maps
        elif cues is None:
            cues = self.scene(maps, light)
        x = inputs = cues
        for enc in self.encoder:
            x = enc(x)
            skips.append(x)
        x = self.fuse(torch.cat([x, self.light(light).to(x.dtype)], 1))
        for i, dec in enumerate(self.decoder):
            if self.config.skips:
                x = torch.cat([x, skips[-1 - i]], 1)
            x = dec(x)
            if self.refine is not None:
                x = self.refine[i](x)
            x = F.interpolate(x, scale_factor=2, mode="bilinear", align_corners=False)
        if self.head is not None:
            x = self.head(torch.cat([x, inputs], 1))
        out = self.out(x)
        if self.config.residual:  # the shade cue's channels are the inputs' last three
            shade = inputs[:, -3:].float().clamp(1e-3, 1 - 1e-3)
            out = out + (torch.log(shade) - torch.log1p(-shade)).to(out.dtype)  # its logit
        return torch.sigmoid(out)


def count_parameters(model: nn.Module) -> int:
    return sum(p.numel() for p in model.parameters())


@torch.no_grad()
def fold_batchnorm(model: NeuralRenderer) -> NeuralRenderer:
    """An inference copy (eval mode) with each BatchNorm folded into the convolution before
    it, using the running statistics: the same outputs with fewer kernels and less traffic."""
    folded = copy.deepcopy(model).eval()
    blocks = [*folded.encoder, folded.fuse, *folded.decoder]
    if getattr(folded, "refine", None) is not None:
        blocks += [block for level in folded.refine for block in level]
    for block in blocks + ([folded.head] if getattr(folded, "head", None) is not None else []):
        conv, bn = block[0], block[1]
        if not isinstance(bn, nn.BatchNorm2d):  # GroupNorm's statistics are the input's own
            continue
        scale = bn.weight / torch.sqrt(bn.running_var + bn.eps)
        conv.weight = nn.Parameter(conv.weight * scale[:, None, None, None])
        conv.bias = nn.Parameter(bn.bias - bn.running_mean * scale)
        block[1] = nn.Identity()
    return folded
