"""Multi-scale SSIM (Wang et al. 2003) as a training loss, its Gaussian windows as matrix products.

The definition is torchmetrics' ``multiscale_structural_similarity_index_measure`` with its
defaults (an 11-tap Gaussian of σ 1.5 over reflection-padded images, K1 0.01, K2 0.03, the
contrast-structure term at every scale but the coarsest, cropped of the padding, the full SSIM
at the coarsest, each clamped at 0 and raised to its weight), and ``tests/test_scene.py`` holds
the two to the same values and gradients. Written here rather than called there because
torchmetrics blurs with a depthwise 2D convolution, whose CPU backward costs more than the
network's own step at 128²; a separable Gaussian over a reflection-padded side of ``n`` pixels
is a fixed ``n x n`` matrix (:func:`blur_matrix`), so each blur is two dense matrix products,
which every backend runs fast forward and backward.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F

from trainer.training.separable import filter_matrix

TAPS = 11
SIGMA = 1.5
K1, K2 = 0.01, 0.03
#: the scales' weights (Wang et al. 2003), finest first
SCALE_WEIGHTS = (0.0448, 0.2856, 0.3001, 0.2363, 0.1333)


def _gaussian(taps: int, sigma: float) -> tuple[float, ...]:
    x = torch.arange(taps, dtype=torch.float64) - taps // 2
    g = torch.exp(-0.5 * (x / sigma) ** 2)
    return tuple((g / g.sum()).tolist())


_GAUSSIAN = _gaussian(TAPS, SIGMA)


def scale_weights(side: int) -> tuple[float, ...]:
    """The weights of the scales that fit a ``side``-pixel image: every scale whose side,
    halved from ``side`` at each, stays wider than the window's reach (10 pixels), at least
    one; the weights kept are renormalised to sum to 1."""
    if side <= TAPS // 2:
        raise ValueError(f"MS-SSIM needs images over {TAPS // 2} pixels a side, not {side}")
    n = max(1, sum(side >> s > TAPS - 1 for s in range(len(SCALE_WEIGHTS))))
    kept = SCALE_WEIGHTS[:n]
    return tuple(w / sum(kept) for w in kept)


def blur_matrix(n: int, device: str = "cpu") -> torch.Tensor:
    """``(n, n)`` fp32: row ``i`` holds the Gaussian taps that output pixel ``i`` takes from
    each input pixel of a reflection-padded side of ``n`` (``A @ x`` blurs ``x``'s rows)."""
    return filter_matrix(_GAUSSIAN, n, "reflect", device)


def _terms(pred: torch.Tensor, target: torch.Tensor, last: bool) -> torch.Tensor:
    """Per image: the mean contrast-structure term (cropped of the padding), or with ``last``
    the mean SSIM."""
    h, w = pred.shape[-2:]
    ah, aw = blur_matrix(h, str(pred.device)), blur_matrix(w, str(pred.device))
    stack = torch.cat([pred, target, pred * pred, target * target, pred * target])
    mp, mt, pp, tt, pt = (ah @ stack @ aw.T).split(pred.shape[0])
    mpp, mtt, mpt = mp * mp, mt * mt, mp * mt
    c1, c2 = K1**2, K2**2
    upper = 2 * (pt - mpt) + c2
    lower = (pp - mpp).clamp(min=0) + (tt - mtt).clamp(min=0) + c2
    if last:
        return ((2 * mpt + c1) * upper / ((mpp + mtt + c1) * lower)).flatten(1).mean(1)
    pad = TAPS // 2
    return (upper / lower)[..., pad : h - pad, pad : w - pad].flatten(1).mean(1)


def ms_ssim(pred: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    """Mean MS-SSIM of ``(N, C, H, W)`` images in [0, 1], computed in fp32."""
    pred, target = pred.float(), target.float()
    weights = scale_weights(min(pred.shape[-2:]))
    with torch.autocast(pred.device.type, enabled=False):  # its variances need fp32
        terms = []
        for i, weight in enumerate(weights):
            last = i == len(weights) - 1
            terms.append(_terms(pred, target, last).clamp(min=0) ** weight)
            if not last:
                pred, target = F.avg_pool2d(pred, 2), F.avg_pool2d(target, 2)
        return torch.stack(terms).prod(0).mean()
