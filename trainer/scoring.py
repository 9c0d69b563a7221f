"""Scores and pictures of display images against their ground truth: PSNR, SSIM and FLIP,
per sample and per material kind (:class:`Tally`), and the labelled picture grid (ground
truth | prediction | error) that ``trainer eval``, the run's held-out scores and the
benchmarks write.

All are computed in the tonemapped display space the network predicts (``[0, 1]``), over the
whole frame. SSIM: Gaussian window 11, σ 1.5, K1 0.01, K2 0.03, per channel, valid region
(Wang et al. 2004).
"""

from __future__ import annotations

from collections import defaultdict
from pathlib import Path

import flip_evaluator
import numpy as np
import torch
import torch.nn.functional as F
from PIL import Image, ImageDraw, ImageFont

from render_jobs.tonemap import to_uint8
from storage.image_files import save_image


def psnr(pred: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    """Per image PSNR in dB of ``(N, C, H, W)`` images in [0, 1] → ``(N,)``."""
    mse = ((pred - target) ** 2).flatten(1).mean(1).clamp_min(1e-12)
    return -10.0 * torch.log10(mse)


def ssim(pred: torch.Tensor, target: torch.Tensor, size: int = 11, sigma: float = 1.5):
    """Per image SSIM of ``(N, C, H, W)`` images in [0, 1] → ``(N,)``."""
    c = pred.shape[1]
    size = min(size, pred.shape[-1], pred.shape[-2])
    g = torch.exp(
        -((torch.arange(size, dtype=torch.float32) - (size - 1) / 2) ** 2) / (2 * sigma**2)
    )
    g = (g / g.sum()).to(pred.device)
    win = (g[:, None] * g[None, :]).expand(c, 1, size, size).contiguous()

    def blur(x):
        return F.conv2d(x, win, groups=c)

    mu_x, mu_y = blur(pred), blur(target)
    sxx = blur(pred * pred) - mu_x**2
    syy = blur(target * target) - mu_y**2
    sxy = blur(pred * target) - mu_x * mu_y
    c1, c2 = 0.01**2, 0.03**2
    s = ((2 * mu_x * mu_y + c1) * (2 * sxy + c2)) / ((mu_x**2 + mu_y**2 + c1) * (sxx + syy + c2))
    return s.flatten(1).mean(1)


def flip(pred: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    """Per image mean LDR-FLIP (NVIDIA's perceptual difference, ``flip-evaluator``; 0 is
    identical, lower is better) of ``(N, 3, H, W)`` sRGB-encoded images in [0, 1] → ``(N,)``."""
    out = []
    for p, t in zip(pred.float().cpu().numpy(), target.float().cpu().numpy(), strict=True):
        ref = np.ascontiguousarray(t.transpose(1, 2, 0))
        test = np.ascontiguousarray(p.transpose(1, 2, 0))
        _, mean, _ = flip_evaluator.evaluate(ref, test, "LDR", inputsRGB=True, applyMagma=False)
        out.append(float(mean))
    return torch.tensor(out)


#: the scores of a :class:`Tally` row, in its order
METRICS = ("psnr", "ssim", "flip")


class Tally:
    """Per-sample PSNR, SSIM and FLIP of display images, kept per material kind."""

    def __init__(self) -> None:
        self.scores: dict[str, list] = defaultdict(list)

    def add(self, pred: torch.Tensor, target: torch.Tensor, kinds: list[str]) -> list[tuple]:
        """Score a batch of ``(N, 3, H, W)`` images in [0, 1]; returns each sample's
        ``(psnr, ssim, flip)``."""
        p, s, f = psnr(pred, target).cpu(), ssim(pred, target).cpu(), flip(pred, target)
        out = []
        for j, kind in enumerate(kinds):
            row = (float(p[j]), float(s[j]), float(f[j]))
            for key in ("all", kind):
                self.scores[key].append(row)
            out.append(row)
        return out

    def summary(self) -> dict:
        """``{"overall": {n, psnr, ssim, flip}, "by_kind": {kind: ...}}`` (means)."""
        kinds = {k: v for k, v in self.scores.items() if k != "all"}
        return {
            "overall": _summary(self.scores["all"]),
            "by_kind": {k: _summary(v) for k, v in sorted(kinds.items())},
        }


def spread(n: int, count: int) -> np.ndarray:
    """``count`` (at most ``n``) sample numbers evenly spaced over ``0 .. n - 1``, first and
    last included: samples of materials far apart in the split, not one material's suns."""
    return np.unique(np.round(np.linspace(0, n - 1, min(count, n))).astype(np.int64))


def _summary(pairs: list) -> dict:
    a = np.array(pairs, np.float64).reshape(-1, 3)
    return {
        "n": len(a),
        "psnr": round(float(a[:, 0].mean()), 3) if len(a) else None,
        "ssim": round(float(a[:, 1].mean()), 4) if len(a) else None,
        "flip": round(float(a[:, 2].mean()), 4) if len(a) else None,
    }


#: tiles of the grid are enlarged (by whole factors, nearest neighbour: every rendered pixel
#: stays one visible block) until they are at least this many pixels wide
GRID_MIN_TILE = 256


GRID_COLUMNS = ("ground truth", "network", "|error| x {gain:g}")


def write_grid(
    path: Path,
    rows: list[tuple[np.ndarray, ...]],
    error_gain: float = 4.0,
    labels: tuple[str, ...] = ("network",),
) -> None:
    """A PNG with one row per sample ``(ground truth, prediction, ...)``: the ground truth,
    each prediction, then each |error| x ``error_gain``, under a header naming the columns
    (``labels`` name the predictions, when there are several); small renders are enlarged
    to be judged by eye."""
    tiles = []
    for gt, *preds in rows:
        errs = [np.clip(np.abs(gt - p).mean(0, keepdims=True) * error_gain, 0, 1) for p in preds]
        tiles.append(np.concatenate([to_uint8(x) for x in (gt, *preds, *errs)], axis=1))
    body = np.concatenate(tiles, axis=0)
    size = rows[0][0].shape[-1]
    factor = max(1, -(-GRID_MIN_TILE // size))
    body = body.repeat(factor, axis=0).repeat(factor, axis=1)
    tile, header = size * factor, 24
    grid = Image.new("RGB", (body.shape[1], body.shape[0] + header), (24, 24, 24))
    grid.paste(Image.fromarray(body), (0, header))
    draw, font = ImageDraw.Draw(grid), ImageFont.load_default(size=14)
    for i, name in enumerate(grid_columns(labels, error_gain)):
        draw.text((i * tile + 6, 4), _fit(draw, name, font, tile - 12), fill=(235, 235, 235),
                  font=font)  # fmt: skip
    save_image(grid, path)


def grid_columns(labels: tuple[str, ...], error_gain: float) -> list[str]:
    """The grid's column names: one prediction's are ``GRID_COLUMNS``; several are named by
    their labels, their errors by their numbers (1 is the first)."""
    if len(labels) == 1:
        return [name.format(gain=error_gain) for name in GRID_COLUMNS]
    errors = [f"|error {i}| x {error_gain:g}" for i in range(1, len(labels) + 1)]
    return ["ground truth", *(f"{i}: {x}" for i, x in enumerate(labels, 1)), *errors]


def _fit(draw, text: str, font, width: int) -> str:
    """``text``, or its end after "..." where the whole is wider than ``width`` pixels."""
    cut = 0
    while (
        cut < len(text) and draw.textlength(("..." if cut else "") + text[cut:], font=font) > width
    ):
        cut += 1
    return ("..." if cut else "") + text[cut:]
