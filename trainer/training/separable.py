"""Separable image filters as dense matrices.

A 1-D filter of ``2r + 1`` taps over one side of ``n`` pixels, padded by reflection or by
repeating the edge, is a fixed ``(n, n)`` matrix, so filtering an image's rows and columns is
``A @ x @ B.T``: two dense matrix products, which every backend runs fast forward and backward.
The losses use it rather than ``conv2d`` because a depthwise 2-D convolution's CPU backward
costs more than the network's own training step at 128².
"""

from __future__ import annotations

import functools

import torch

PADS = ("reflect", "replicate")


@functools.lru_cache(maxsize=64)
def filter_matrix(taps: tuple[float, ...], n: int, pad: str, device: str = "cpu") -> torch.Tensor:
    """``(n, n)`` fp32: row ``i`` holds the weights output pixel ``i`` takes from each input
    pixel when ``taps`` (odd length, centred) filter a side of ``n`` padded by ``pad``:
    ``reflect`` mirrors without repeating the edge pixel, ``replicate`` repeats it."""
    if len(taps) % 2 == 0:
        raise ValueError(f"a centred filter has an odd number of taps, not {len(taps)}")
    if pad not in PADS:
        raise ValueError(f"pad is one of {PADS}, not {pad!r}")
    r = len(taps) // 2
    src = torch.arange(n)[:, None] + torch.arange(-r, r + 1)[None, :]
    if pad == "reflect":
        src = src.abs()
        src = torch.where(src >= n, 2 * (n - 1) - src, src)
    src = src.clamp(0, n - 1)  # replicate; a no-op after reflecting a side longer than r
    w = torch.tensor(taps, dtype=torch.float64).expand_as(src)
    a = torch.zeros(n, n, dtype=torch.float64)
    a.index_put_((torch.arange(n)[:, None].expand_as(src), src), w, accumulate=True)
    return a.float().to(device)


def filter2d(x: torch.Tensor, rows: tuple[float, ...], cols: tuple[float, ...], pad: str):
    """``(..., H, W)`` filtered by ``cols`` along H and ``rows`` along W (the 2-D filter
    ``cols[:, None] * rows[None, :]``), padded by ``pad``."""
    h, w = x.shape[-2:]
    dev = str(x.device)
    return filter_matrix(cols, h, pad, dev) @ x @ filter_matrix(rows, w, pad, dev).T
