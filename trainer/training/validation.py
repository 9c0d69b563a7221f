"""Held-out scores while a run trains: the network's PSNR and SSIM on a fixed set of its run's
held-out samples, scored as ``trainer eval`` scores them (fp32, the tonemapped display space,
the same :func:`trainer.rendering.evaluate.psnr` and :func:`trainer.rendering.evaluate.ssim`), so
that the curve shows when the network stops improving on materials it never trains on. FLIP is left
to ``trainer eval``: it runs on the CPU, image by image.

The samples are ``count`` evenly spaced ones of the held-out split (every one when it has
fewer), the same at every score of a run, read from the stores each time (nothing is kept in
memory between scores). Only rank 0 scores (``trainer.training.train``), with the bare network the
checkpoints render with: no collective runs, so the other ranks wait at their next gradient
all-reduce. A run with ``--ema-decay`` renders with the moving average of its weights, and
scores the trained weights too on the same batches (``others``), so that its curves show what
the average gains.

Each score carries how sure it is (:mod:`trainer.intervals`): the PSNR's interval over the
samples' materials, which says how far the mean over all materials like these may lie, and
:meth:`Validator.against`, the paired difference from an earlier score on the same samples,
which says whether a move between two scores is more than the materials' spread. The two
differ: as both scores share the samples, a move inside the first interval can be resolved.
"""

from __future__ import annotations

import time

import numpy as np
import torch

from trainer.intervals import cluster_mean, paired_difference
from trainer.samples import SampleReader, samples_digest
from trainer.scoring import psnr, spread, ssim
from trainer.targets import Tonemap, model_inputs
from trainer.training.data import Split


class Validator:
    """Scores a network on ``count`` evenly spaced samples of ``split``, ``batch_size`` at a
    time."""

    def __init__(self, split: Split, count: int, batch_size: int = 8):
        self.ids = spread(len(split), count)
        self.of = len(split)
        self.digest = samples_digest(split, self.ids)
        self.reader = SampleReader(split)
        self.batch_size = batch_size
        #: each sample's material as ``(store, material)``, for the intervals
        self.groups = np.array(
            [(s, self.reader.stores[s].layout.material_of_sample(int(k)))
             for s, k in split.refs[self.ids]],
            np.int64,
        ).reshape(-1, 2)  # fmt: skip

    def __len__(self) -> int:
        return len(self.ids)

    @torch.inference_mode()
    def score(
        self,
        model: torch.nn.Module,
        roughness_channels: int,
        tonemap: Tonemap,
        fmt: torch.memory_format = torch.contiguous_format,
        shown: int = 0,
        others: dict[str, torch.nn.Module] | None = None,
    ) -> tuple[dict, list[tuple[np.ndarray, np.ndarray]], np.ndarray]:
        """``{"samples", "psnr", "ssim", "materials", "psnr_low", "psnr_high", "seconds"}``:
        the means over the samples of ``model`` on its device, with the PSNR's interval over
        the materials (None under :data:`trainer.intervals.MIN_MATERIALS`), and ``NAME_psnr``
        and ``NAME_ssim`` of each ``NAME: model`` of ``others`` on the same batches (each read
        once); every model is put in eval mode for the scores, then back in the mode it was
        in. Also the ``(ground truth, prediction)`` display images of ``model``'s first
        ``shown`` samples (for :func:`trainer.rendering.evaluate.write_grid`), and ``model``'s PSNR
        of each sample (for :func:`against`)."""
        t0 = time.perf_counter()
        device = next(model.parameters()).device
        models = {"": model, **(others or {})}
        modes = {name: m.training for name, m in models.items()}
        scores = {name: [] for name in models}
        pictures = []
        try:
            for m in models.values():
                m.eval()
            for lo in range(0, len(self.ids), self.batch_size):
                batch = self.reader.batch(self.ids[lo : lo + self.batch_size])
                x = model_inputs(batch["maps"].to(device), roughness_channels)
                x = x.contiguous(memory_format=fmt)
                light = batch["light"].to(device, torch.float32)
                target = tonemap(batch["render"].to(device))
                for name, m in models.items():
                    pred = m(x, light).float()
                    scores[name].append(torch.stack([psnr(pred, target), ssim(pred, target)], 1))
                    if name == "":
                        for j in range(min(shown - len(pictures), len(pred))):
                            pictures.append((target[j].cpu().numpy(), pred[j].cpu().numpy()))
        finally:
            for name, m in models.items():
                m.train(modes[name])
        out = {"samples": len(self.ids)}
        for name, rows in scores.items():
            mean = torch.cat(rows).double().mean(0).cpu() if rows else torch.full((2,), torch.nan)
            prefix = f"{name}_" if name else ""
            out[prefix + "psnr"] = round(float(mean[0]), 4)
            out[prefix + "ssim"] = round(float(mean[1]), 5)
        each = torch.cat(scores[""])[:, 0].double().cpu().numpy() if scores[""] else np.zeros(0)
        m = cluster_mean(each, self.groups)
        out.update(materials=m["materials"], psnr_low=_rounded(m["low"]))
        out["psnr_high"] = _rounded(m["high"])
        out["seconds"] = round(time.perf_counter() - t0, 3)
        return out, pictures, each

    def against(self, base: np.ndarray, now: np.ndarray) -> dict:
        """``now - base``, two scores' per-sample PSNRs, as ``{"mean", "low", "high"}``
        (:func:`trainer.intervals.paired_difference` over the samples' materials)."""
        d = paired_difference(base, now, self.groups)
        return {"mean": round(d["mean"], 4), "low": _rounded(d["low"]), "high": _rounded(d["high"])}


def _rounded(v: float | None) -> float | None:
    return None if v is None else round(v, 4)
