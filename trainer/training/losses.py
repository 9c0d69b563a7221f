"""The losses: the paper's L1 + the VGG16 relu3_3 feature reconstruction loss (Johnson et al.
2016), its L1 ablation, L1 + MS-SSIM (Zhao et al. 2017, OIDN's default) and L1 + LDR-FLIP
(:mod:`trainer.training.flip`); the last two need no pretrained weights and mix their term
with L1 in Zhao et al.'s proportions, so they differ in that term alone.

VGG16's convolutional trunk up to relu3_3 is defined here, with the layer indices of
torchvision's ``vgg16().features`` (0..15), so a torchvision-format state dict loads into it
(``features.N.weight`` / ``features.N.bias``; the classifier is ignored). ImageNet weights are
never downloaded: they come from ``--vgg-weights FILE`` or the torch hub cache
(``$TORCH_HOME/hub/checkpoints/vgg16-*.pth``, where ``torchvision.models.vgg16(weights=...)``
leaves them). Inputs in [0, 1] are normalised with ImageNet mean and std.
"""

from __future__ import annotations

import glob
import os
from pathlib import Path

import torch
import torch.nn.functional as F
from torch import nn

from shaderball.errors import UserError
from trainer.training.flip import flip_loss
from trainer.training.msssim import ms_ssim

# torchvision's vgg16 "features" up to relu3_3: conv channels, "M" = max pool
_TRUNK = [64, 64, "M", 128, 128, "M", 256, 256, 256]
MEAN = (0.485, 0.456, 0.406)
STD = (0.229, 0.224, 0.225)
HUB_PATTERN = "vgg16-*.pth"


class MissingWeightsError(UserError, FileNotFoundError):
    """The perceptual loss was asked for without VGG16 weights."""


def vgg16_relu3_3() -> nn.Sequential:
    """VGG16 ``features[:16]`` (untrained): ``(N, 3, H, W)`` → ``(N, 256, H/4, W/4)``."""
    layers: list[nn.Module] = []
    cin = 3
    for v in _TRUNK:
        if v == "M":
            layers.append(nn.MaxPool2d(2, 2))
        else:
            layers += [nn.Conv2d(cin, v, 3, padding=1), nn.ReLU(inplace=True)]
            cin = v
    return nn.Sequential(*layers)


def find_weights(path: str | os.PathLike | None = None) -> Path:
    """The VGG16 weights file: ``path`` if given, else the newest in the torch hub cache."""
    if path is not None:
        p = Path(path)
        if not p.is_file():
            raise MissingWeightsError(f"VGG16 weights file {p} does not exist")
        return p
    hub = Path(torch.hub.get_dir()) / "checkpoints"
    found = sorted(glob.glob(str(hub / HUB_PATTERN)))
    if not found:
        raise MissingWeightsError(
            f"the perceptual loss needs ImageNet VGG16 weights and none are in {hub}: pass "
            "--vgg-weights FILE (a torchvision vgg16 state dict, e.g. vgg16-397923af.pth), "
            "copy that file into the hub cache, or train with --loss l1"
        )
    return Path(found[-1])


def load_vgg(path: str | os.PathLike | None = None) -> nn.Sequential:
    """The relu3_3 trunk with weights from a torchvision-format state dict (frozen, eval)."""
    file = find_weights(path)
    try:
        state = torch.load(file, map_location="cpu", weights_only=True)
    except Exception as exc:  # torch raises several types for a bad file
        raise MissingWeightsError(f"{file}: not a readable torch state dict ({exc})") from None
    trunk = vgg16_relu3_3()
    want = {f"features.{k}": v for k, v in trunk.state_dict().items()}
    missing = [k for k in want if k not in state]
    if missing:
        raise MissingWeightsError(f"{file}: not VGG16 weights (no {missing[0]})")
    for k, v in want.items():
        if tuple(state[k].shape) != tuple(v.shape):
            raise MissingWeightsError(
                f"{file}: {k} has shape {tuple(state[k].shape)}, VGG16 has {tuple(v.shape)}"
            )
    trunk.load_state_dict({k.removeprefix("features."): state[k] for k in want})
    trunk.eval().requires_grad_(False)
    return trunk


#: Zhao et al.'s weight of the MS-SSIM term (L1 gets the rest); the FLIP term's too
MIX_WEIGHT = 0.84
#: the terms mixed with L1: name → ``(pred, target)`` → scalar, 0 for equal images
TERMS = {
    "msssim": lambda pred, target: 1 - ms_ssim(pred, target),
    "flip": flip_loss,
}


def mixed_term(loss: str) -> str | None:
    """The term a ``--loss`` name mixes with L1 (``l1+flip`` → ``flip``), None for the rest."""
    term = loss.removeprefix("l1+")
    return term if term in TERMS else None


class MixedLoss(nn.Module):
    """``(N, 3, H, W)`` images in [0, 1] → ``0.84 term + 0.16 L1`` in fp32 (Zhao et al. 2017's
    mix), ``term`` one of :data:`TERMS`."""

    def __init__(self, term: str):
        super().__init__()
        if term not in TERMS:
            raise ValueError(f"the term mixed with L1 is one of {', '.join(TERMS)}, not {term!r}")
        self.term = term

    def forward(self, pred: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
        pred, target = pred.float(), target.float()
        term = TERMS[self.term](pred, target)
        return MIX_WEIGHT * term + (1 - MIX_WEIGHT) * F.l1_loss(pred, target)


class RendererLoss(nn.Module):
    """``loss(pred, target)`` for ``(N, 3, H, W)`` images in [0, 1]: L1, plus
    ``perceptual_weight`` × MSE of relu3_3 features when a VGG trunk is given; or, with
    ``mixed`` (a name in :data:`TERMS`), :class:`MixedLoss`."""

    def __init__(
        self,
        vgg: nn.Module | None = None,
        perceptual_weight: float = 1.0,
        mixed: str | None = None,
    ):
        super().__init__()
        if vgg is not None and mixed:
            raise ValueError(f"the loss is L1 + VGG16 or L1 + {mixed}, not both")
        self.vgg = vgg
        self.perceptual_weight = perceptual_weight
        self.mixed = MixedLoss(mixed) if mixed else None
        self.register_buffer("mean", torch.tensor(MEAN).view(1, 3, 1, 1), persistent=False)
        self.register_buffer("std", torch.tensor(STD).view(1, 3, 1, 1), persistent=False)

    def forward(self, pred: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
        """Scalar fp32 loss. Under autocast the VGG convolutions run in its dtype (bf16 on
        CUDA); the L1 and the feature MSE are always computed in fp32."""
        pred, target = pred.float(), target.float()
        if self.mixed is not None:
            return self.mixed(pred, target)
        loss = F.l1_loss(pred, target)
        if self.vgg is not None:
            fp = self.vgg((pred - self.mean) / self.std)
            with torch.no_grad():  # no backward through the target's half
                ft = self.vgg((target - self.mean) / self.std)
            loss = loss + self.perceptual_weight * F.mse_loss(fp.float(), ft.float())
        return loss
