"""Evaluation on the held-out materials: PSNR and SSIM, overall and per material kind.

Both are computed in the tonemapped display space the model predicts (``[0, 1]``), over the
whole frame. SSIM: Gaussian window 11, σ 1.5, K1 0.01, K2 0.03, per channel, valid region
(Wang et al. 2004). The held-out materials are the ones the checkpoint's run never trained on.
"""

from __future__ import annotations

from collections import defaultdict
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F
from PIL import Image
from tqdm import tqdm

from render_jobs.tonemap import to_uint8
from trainer.data import Catalog, SampleReader
from trainer.infer import Renderer


class EvalError(ValueError):
    """Nothing to evaluate, or stores that do not match the checkpoint."""


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
    import flip_evaluator

    out = []
    for p, t in zip(pred.float().cpu().numpy(), target.float().cpu().numpy(), strict=True):
        ref = np.ascontiguousarray(t.transpose(1, 2, 0))
        test = np.ascontiguousarray(p.transpose(1, 2, 0))
        _, mean, _ = flip_evaluator.evaluate(ref, test, "LDR", inputsRGB=True, applyMagma=False)
        out.append(float(mean))
    return torch.tensor(out)


def evaluate(
    ckpt,
    stores: list[str] | None = None,
    batch_size: int = 8,
    grid: Path | None = None,
    grid_count: int = 4,
    device: str = "auto",
) -> dict:
    """Metrics of checkpoint ``ckpt`` on its run's held-out split (``stores``: the same stores
    by another address, e.g. a local copy); writes a ground truth | prediction | error PNG grid
    of the first ``grid_count`` held-out samples to ``grid`` when given."""
    renderer = Renderer.from_checkpoint(ckpt, device)
    catalog = Catalog.from_dict(renderer.state["catalog"])
    if stores:
        if len(stores) != len(catalog.urls):
            raise EvalError(
                f"the checkpoint's run trained on {len(catalog.urls)} store(s) "
                f"({', '.join(catalog.urls)}), {len(stores)} given"
            )
        catalog.urls = list(stores)
    split = catalog.split("test")
    if len(split) == 0:
        raise EvalError(
            "no held-out samples: the run held out no materials (train with --holdout-fraction > 0)"
        )
    reader = SampleReader(split)
    kinds = [{m: rec["kind"] for m, rec in s.materials().items()} for s in reader.stores]
    scores: dict[str, list] = defaultdict(list)
    shown = []
    ids = np.arange(len(split))
    for lo in tqdm(range(0, len(ids), batch_size), desc="eval", unit="batch"):
        batch = reader.batch(ids[lo : lo + batch_size])
        pred = renderer.render_batch(batch["maps"], batch["light"])
        target = renderer.tonemap(batch["render"].to(pred.device))
        p, s, f = psnr(pred, target).cpu(), ssim(pred, target).cpu(), flip(pred, target)
        for j, i in enumerate(batch["id"].tolist()):
            store, sample = split.refs[i]
            layout = reader.stores[store].layout
            kind = kinds[store][layout.material_of_sample(int(sample))]
            for key in ("all", kind):
                scores[key].append((float(p[j]), float(s[j]), float(f[j])))
            if len(shown) < grid_count:
                shown.append((target[j].cpu().numpy(), pred[j].cpu().numpy()))
    result = {
        "checkpoint_step": int(renderer.state["step"]),
        "samples": len(split),
        "overall": _summary(scores.pop("all")),
        "by_kind": {k: _summary(v) for k, v in sorted(scores.items())},
    }
    if grid is not None:
        write_grid(grid, shown)
        result["grid"] = str(grid)
    return result


def _summary(pairs: list) -> dict:
    a = np.array(pairs, np.float64)
    return {
        "n": len(a),
        "psnr": round(float(a[:, 0].mean()), 3),
        "ssim": round(float(a[:, 1].mean()), 4),
        "flip": round(float(a[:, 2].mean()), 4),
    }


#: tiles of the grid are enlarged (by whole factors, nearest neighbour: every rendered pixel
#: stays one visible block) until they are at least this many pixels wide
GRID_MIN_TILE = 256
GRID_COLUMNS = ("ground truth", "network", "|error| x {gain:g}")


def write_grid(
    path: Path, rows: list[tuple[np.ndarray, np.ndarray]], error_gain: float = 4.0
) -> None:
    """A PNG with one row per sample: ground truth | prediction | |error| x ``error_gain``,
    under a header naming the columns; small renders are enlarged to be judged by eye."""
    from PIL import ImageDraw, ImageFont

    tiles = []
    for gt, pred in rows:
        err = np.clip(np.abs(gt - pred).mean(0, keepdims=True) * error_gain, 0, 1)
        tiles.append(np.concatenate([to_uint8(gt), to_uint8(pred), to_uint8(err)], axis=1))
    body = np.concatenate(tiles, axis=0)
    size = rows[0][0].shape[-1]
    factor = max(1, -(-GRID_MIN_TILE // size))
    body = body.repeat(factor, axis=0).repeat(factor, axis=1)
    tile, header = size * factor, 24
    grid = Image.new("RGB", (body.shape[1], body.shape[0] + header), (24, 24, 24))
    grid.paste(Image.fromarray(body), (0, header))
    draw, font = ImageDraw.Draw(grid), ImageFont.load_default(size=14)
    for i, name in enumerate(GRID_COLUMNS):
        draw.text((i * tile + 6, 4), name.format(gain=error_gain), fill=(235, 235, 235), font=font)
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    grid.save(path)
