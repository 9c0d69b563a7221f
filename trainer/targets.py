"""What the network sees and what it must produce, as tensors.

Inputs: the stored maps ``(N, 11, H, W) uint8`` (``storage.schema``: diffuse and specular
sRGB-encoded, roughness, normal, mask) become ``(N, C, H, W) float`` in [0, 1] by dropping the
mask and dividing by 255 — colours stay sRGB-encoded, as the authors' PNG inputs were.
Light: ``(N, 4)`` = unit sun direction (z up) and turbidity / 10.

Target: the fixed tonemap of the linear HDR render, ``srgb(y / (1 + y))`` with
``y = radiance * 2**exposure`` (Reinhard per channel, then the sRGB curve; exposure +1 stop),
the same curve as ``render_jobs.tonemap`` uses for previews. Its parameters are stored in every
checkpoint (:meth:`Tonemap.to_dict`) so inference and evaluation reproduce it.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np
import torch

from render_jobs.tonemap import DEFAULT_EXPOSURE

TURBIDITY_SCALE = 10.0
CURVES = ("reinhard",)


@dataclass(frozen=True)
class Tonemap:
    exposure: float = DEFAULT_EXPOSURE
    curve: str = "reinhard"
    encoding: str = "srgb"

    def __post_init__(self) -> None:
        if self.curve not in CURVES or self.encoding != "srgb":
            raise ValueError(f"unknown tonemap {self.curve}/{self.encoding}")

    def __call__(self, radiance: torch.Tensor) -> torch.Tensor:
        """Linear HDR ``(N, 3, H, W)`` (any float dtype) → ``(N, 3, H, W) float32`` in [0, 1]."""
        y = radiance.float().clamp_min(0.0) * (2.0**self.exposure)
        return srgb_encode(y / (1.0 + y)).clamp(0.0, 1.0)

    def to_dict(self) -> dict:
        return asdict(self)

    @classmethod
    def from_dict(cls, d: dict) -> Tonemap:
        return cls(**d)


def srgb_encode(x: torch.Tensor) -> torch.Tensor:
    x = x.clamp_min(0.0)
    return torch.where(x <= 0.0031308, 12.92 * x, 1.055 * x.clamp_min(1e-8) ** (1 / 2.4) - 0.055)


def srgb_decode(x: torch.Tensor) -> torch.Tensor:
    """IEC 61966-2-1 sRGB decode of values in [0, 1]."""
    return torch.where(x <= 0.04045, x / 12.92, ((x + 0.055) / 1.055) ** 2.4)


def model_inputs(packed: torch.Tensor, roughness_channels: int = 1) -> torch.Tensor:
    """Stored maps ``(N, 11, H, W) uint8`` → network input ``(N, 9 + r, H, W) float32``."""
    if packed.dim() != 4 or packed.shape[1] != 11:
        raise ValueError(f"packed maps have shape {tuple(packed.shape)}, expected (N, 11, H, W)")
    x = packed[:, :10].float() / 255.0
    if roughness_channels == 3:
        x = torch.cat([x[:, :6], x[:, 6:7].expand(-1, 3, -1, -1), x[:, 7:10]], 1)
    return x


def light_vector(direction, turbidity) -> np.ndarray:
    """Sun direction(s) ``(..., 3)`` (normalised here) and turbidity ``(...)`` → ``(..., 4)
    float32``: the light encoder's input."""
    d = np.asarray(direction, dtype=np.float64)
    norm = np.linalg.norm(d, axis=-1, keepdims=True)
    if np.any(norm == 0):
        raise ValueError("sun direction must not be the zero vector")
    t = np.asarray(turbidity, dtype=np.float64)[..., None] / TURBIDITY_SCALE
    return np.concatenate([d / norm, t], -1).astype(np.float32)
