"""How sure a mean score is: intervals of a bootstrap over whole materials.

A held-out set holds each material under several suns, and a material's samples are not
independent draws: a network that does badly on one material does badly under all its suns.
So the interval of a mean resamples the materials whole (a cluster bootstrap), and paired
scores (two methods on the same samples) are compared through their per-sample differences.
``trainer eval --checkpoint A --checkpoint B`` and the quality report (``make quality``) both
use these. Plain numpy; ``groups`` name each sample's material, as ints or as rows of ints
(``(store, material)`` pairs).

Hand-written because ``scipy.stats.bootstrap`` resamples single observations, not clusters of
them.
"""

from __future__ import annotations

import numpy as np

#: the bootstrap's resamples and coverage; a fixed seed keeps a printed interval the same run
#: to run
RESAMPLES, LEVEL, SEED = 2000, 0.95, 0
#: fewer materials than this give no interval: a bootstrap over so few says little
MIN_MATERIALS = 5


def cluster_mean(values, groups, resamples: int = RESAMPLES) -> dict:
    """Mean of ``values`` (one a sample) with the ``LEVEL`` interval of a bootstrap that
    resamples the samples' ``groups`` (materials) whole: ``{"mean", "low", "high",
    "materials"}``. ``low`` and ``high`` are ``None`` under ``MIN_MATERIALS`` groups."""
    v = np.asarray(values, np.float64).reshape(-1)
    if len(v) == 0:
        return {"mean": None, "materials": 0, "low": None, "high": None}
    gs = np.asarray(groups)
    _, g = np.unique(gs[:, None] if gs.ndim == 1 else gs, axis=0, return_inverse=True)
    g = g.reshape(-1)
    n = int(g.max()) + 1
    out = {"mean": float(v.mean()), "materials": n}
    if n < MIN_MATERIALS:
        return {**out, "low": None, "high": None}
    sums, counts = np.bincount(g, v, n), np.bincount(g, None, n)
    pick = np.random.default_rng(SEED).integers(0, n, (resamples, n))
    means = sums[pick].sum(1) / counts[pick].sum(1)
    tail = (1 - LEVEL) / 2 * 100
    low, high = np.percentile(means, [tail, 100 - tail])
    return {**out, "low": float(low), "high": float(high)}


def paired_difference(base, other, groups, resamples: int = RESAMPLES) -> dict:
    """Mean of ``other - base`` over paired samples with its :func:`cluster_mean` interval,
    and the share of samples where ``other`` is the higher (``"higher"``)."""
    d = np.asarray(other, np.float64) - np.asarray(base, np.float64)
    return {**cluster_mean(d, groups, resamples), "higher": float((d > 0).mean())}


def bracket(low: float | None, high: float | None, fmt: str = ".2f") -> str:
    """An interval as the reports print it, ``[25.81, 26.58]``, or ``—`` for none."""
    return "—" if low is None else f"[{low:{fmt}}, {high:{fmt}}]"


def excludes_zero(d: dict) -> bool:
    """Whether an interval of :func:`cluster_mean` or :func:`paired_difference` lies wholly
    on one side of 0 (False without an interval)."""
    return d["low"] is not None and (d["low"] > 0 or d["high"] < 0)
