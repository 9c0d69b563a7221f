"""LDR-FLIP (Andersson et al. 2020, "FLIP: A Difference Evaluator for Alternating Images") as
a differentiable training loss.

``trainer eval`` scores FLIP with NVIDIA's ``flip-evaluator``, which runs in C++ on NumPy
arrays and has no gradient, and no package on the registry offers one in torch, so the metric
is written here from the paper, with ``flip-evaluator``'s observer (67 pixels per degree: a
0.7 m wide 4K screen seen from 0.7 m). ``tests/test_flip_loss.py`` holds the two to the same
values.

Two pipelines compare display images (sRGB-encoded, [0, 1]):

- colour: each image in the opponent space YCxCz is filtered by the eye's contrast
  sensitivity per channel (sums of Gaussians), taken back to linear RGB and clamped, then
  to Hunt-adjusted L*a*b*; the per-pixel HyAB distance, raised to ``QC``, is spread over
  [0, 1] against the largest (green against blue).
- features: edges and points of the luminance, found with the first and second derivatives
  of a Gaussian as wide as the eye's edge detector; the larger difference in their strength,
  raised to ``QF``.

Per pixel, ``colour ** (1 - feature)``: a feature difference lifts the colour error. Every
filter is separable and applied as two matrix products (:mod:`trainer.training.separable`,
edges repeated as in FLIP). The square roots and powers are kept off zero (``EPS``) so the
gradient stays finite where the images agree.
"""

from __future__ import annotations

import functools
import math

import torch

from trainer.targets import srgb_decode
from trainer.training.separable import filter2d

#: flip-evaluator's default observer: a 0.7 m wide 3840-pixel screen at 0.7 m
PIXELS_PER_DEGREE = 0.7 * 3840 / 0.7 * math.pi / 180
QC, QF, PC, PT = 0.7, 0.5, 0.4, 0.95
EPS = 1e-15
#: contrast sensitivity per opponent channel: (a1, b1, a2, b2) of
#: ``a1 sqrt(pi / b1) exp(-pi² r² / b1) + a2 sqrt(pi / b2) exp(-pi² r² / b2)``, r in degrees
CSF = {
    "A": (1.0, 0.0047, 0.0, 1e-5),
    "RG": (1.0, 0.0053, 0.0, 1e-5),
    "BY": (34.1, 0.04, 13.5, 0.025),
}
#: peak-to-trough width of the eye's edge detector, in degrees
EDGE_WIDTH = 0.082
#: sRGB primaries and D65 white, CIE xy
PRIMARIES = ((0.64, 0.33), (0.30, 0.60), (0.15, 0.06))
WHITE = (0.3127, 0.3290)


def _xyz(xy: tuple[float, float]) -> torch.Tensor:
    x, y = xy
    return torch.tensor([x / y, 1.0, (1 - x - y) / y], dtype=torch.float64)


@functools.cache
def rgb_to_xyz() -> torch.Tensor:
    """``(3, 3)`` float64: linear sRGB → CIE XYZ, from the primaries and the D65 white."""
    p = torch.stack([_xyz(c) for c in PRIMARIES], 1)
    return p * torch.linalg.solve(p, _xyz(WHITE))[None, :]


@functools.cache
def xyz_to_rgb() -> torch.Tensor:
    """``(3, 3)`` float64: CIE XYZ → linear sRGB."""
    return torch.linalg.inv(rgb_to_xyz())


def _mix(m: torch.Tensor, x: torch.Tensor) -> torch.Tensor:
    """``(3, 3)`` matrix applied to the channels of ``(N, 3, H, W)``."""
    return torch.einsum("ij,njhw->nihw", m.to(x), x)


def _white() -> torch.Tensor:
    return rgb_to_xyz().sum(1).view(1, 3, 1, 1)


def to_ycxcz(linear: torch.Tensor) -> torch.Tensor:
    """Linear sRGB → YCxCz (the linear opponent space of L*a*b*)."""
    x, y, z = (_mix(rgb_to_xyz(), linear) / _white().to(linear)).unbind(1)
    return torch.stack([116 * y - 16, 500 * (x - y), 200 * (y - z)], 1)


def from_ycxcz(o: torch.Tensor) -> torch.Tensor:
    """YCxCz → linear sRGB."""
    y = (o[:, 0] + 16) / 116
    xyz = torch.stack([y + o[:, 1] / 500, y, y - o[:, 2] / 200], 1) * _white().to(o)
    return _mix(xyz_to_rgb(), xyz)


def to_hunt_lab(linear: torch.Tensor) -> torch.Tensor:
    """Linear sRGB → L*a*b* with a* and b* scaled by L* / 100 (the Hunt effect)."""
    t = _mix(rgb_to_xyz(), linear) / _white().to(linear)
    d = 6 / 29
    f = torch.where(t > d**3, t.clamp(min=d**3) ** (1 / 3), t / (3 * d * d) + 4 / 29)
    lum = 116 * f[:, 1] - 16
    a, b = 500 * (f[:, 0] - f[:, 1]), 200 * (f[:, 1] - f[:, 2])
    return torch.stack([lum, lum * a / 100, lum * b / 100], 1)


def hyab(p: torch.Tensor, q: torch.Tensor) -> torch.Tensor:
    """``(N, 1, H, W)`` HyAB distance: |ΔL| + ||Δ(a, b)||."""
    d = p - q
    return ((d[:, :1] ** 2).clamp(min=EPS).sqrt() + (d[:, 1:] ** 2).sum(1, keepdim=True)
            .clamp(min=EPS).sqrt())  # fmt: skip


def _csf_terms(channel: str, ppd: float, radius: int) -> list[tuple[float, tuple[float, ...]]]:
    """The channel's filter as (weight, 1-D taps) Gaussians whose outer products sum to it."""
    a1, b1, a2, b2 = CSF[channel]
    r = torch.arange(-radius, radius + 1, dtype=torch.float64) / ppd
    terms = [(a * math.sqrt(math.pi / b), torch.exp(-(math.pi**2) * r * r / b))
             for a, b in ((a1, b1), (a2, b2)) if a]  # fmt: skip
    total = sum(w * float(g.sum()) ** 2 for w, g in terms)
    return [(w / total, tuple(g.tolist())) for w, g in terms]


def csf_filter(o: torch.Tensor, ppd: float) -> torch.Tensor:
    """YCxCz filtered per channel by its contrast sensitivity (kernels normalised to 1)."""
    widest = max(b for a1, b1, a2, b2 in CSF.values() for b in (b1, b2))
    radius = math.ceil(3 * math.sqrt(widest / (2 * math.pi**2)) * ppd)
    out = []
    for c, channel in enumerate(CSF):
        plane = o[:, c : c + 1]
        out.append(sum(w * filter2d(plane, g, g, "replicate")
                       for w, g in _csf_terms(channel, ppd, radius)))  # fmt: skip
    return torch.cat(out, 1)


def _signed_unit(t: torch.Tensor) -> tuple[float, ...]:
    """Taps with the positive ones scaled to sum to 1 and the negative ones to -1."""
    pos, neg = t.clamp(min=0).sum(), -t.clamp(max=0).sum()
    return tuple(torch.where(t > 0, t / pos, t / neg).tolist())


@functools.cache
def feature_taps(ppd: float, kind: str) -> tuple[tuple[float, ...], tuple[float, ...]]:
    """(across, along) taps of the edge (first derivative of a Gaussian) or point (second
    derivative) detector; the 2-D kernel ``along[:, None] * across[None, :]`` with its
    positive and negative weights each summing to ±1."""
    sd = 0.5 * EDGE_WIDTH * ppd
    x = torch.arange(-math.ceil(3 * sd), math.ceil(3 * sd) + 1, dtype=torch.float64)
    g = torch.exp(-x * x / (2 * sd * sd))
    d = -x * g if kind == "edge" else (x * x / (sd * sd) - 1) * g
    return _signed_unit(d), tuple((g / g.sum()).tolist())


def _strength(y: torch.Tensor, ppd: float, kind: str) -> torch.Tensor:
    """``(N, 1, H, W)`` length of the detector's (x, y) response."""
    across, along = feature_taps(ppd, kind)
    fx = filter2d(y, across, along, "replicate")
    fy = filter2d(y, along, across, "replicate")
    return (fx * fx + fy * fy).clamp(min=EPS).sqrt()


@functools.cache
def _cmax() -> float:
    """The largest colour error: pure green against pure blue, raised to ``QC``."""
    green = torch.tensor([0.0, 1.0, 0.0], dtype=torch.float64).view(1, 3, 1, 1)
    blue = torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64).view(1, 3, 1, 1)
    return float(hyab(to_hunt_lab(green), to_hunt_lab(blue))) ** QC


def flip_map(pred: torch.Tensor, target: torch.Tensor, ppd: float = PIXELS_PER_DEGREE):
    """``(N, 1, H, W)`` per-pixel LDR-FLIP of ``(N, 3, H, W)`` sRGB-encoded images in [0, 1]
    (clamped), computed in fp32."""
    with torch.autocast(pred.device.type, enabled=False):
        o_pred, o_target = (to_ycxcz(srgb_decode(x.float().clamp(0, 1)))
                            for x in (pred, target))  # fmt: skip
        lab = [to_hunt_lab(from_ycxcz(csf_filter(o, ppd)).clamp(0, 1))
               for o in (o_pred, o_target)]  # fmt: skip
        cmax = _cmax()
        e = hyab(*lab) ** QC
        knee = PC * cmax
        colour = torch.where(e < knee, e * (PT / knee), PT + (e - knee) / (cmax - knee) * (1 - PT))
        y_pred, y_target = (o_pred[:, :1] + 16) / 116, (o_target[:, :1] + 16) / 116
        diff = [(_strength(y_pred, ppd, k) - _strength(y_target, ppd, k)).abs()
                for k in ("edge", "point")]  # fmt: skip
        feature = (torch.maximum(*diff).clamp(min=EPS) / math.sqrt(2)) ** QF
        return colour ** (1 - feature)


def flip_loss(pred: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    """Mean LDR-FLIP of a batch of display images (the mean of ``trainer eval``'s FLIP)."""
    return flip_map(pred, target).mean()
