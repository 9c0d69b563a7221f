"""Held-out scores while a run trains: the network's PSNR and SSIM on a fixed set of its run's
held-out samples, scored as ``trainer eval`` scores them (fp32, the tonemapped display space,
the same :func:`trainer.evaluate.psnr` and :func:`trainer.evaluate.ssim`), so that the curve
shows when the network stops improving on materials it never trains on. FLIP is left to
``trainer eval``: it runs on the CPU, image by image.

The samples are ``count`` evenly spaced ones of the held-out split (every one when it has
fewer), the same at every score of a run, read from the stores each time (nothing is kept in
memory between scores). Only rank 0 scores (``trainer.train``), with the bare network the
checkpoints render with (the moving average of a run with ``--ema-decay``): no collective
runs, so the other ranks wait at their next gradient all-reduce.
"""

from __future__ import annotations

import time

import numpy as np
import torch

from trainer.data import SampleReader, Split
from trainer.evaluate import psnr, ssim
from trainer.targets import Tonemap, model_inputs


class Validator:
    """Scores a network on ``count`` evenly spaced samples of ``split``, ``batch_size`` at a
    time."""

    def __init__(self, split: Split, count: int, batch_size: int = 8):
        k = min(count, len(split))
        spaced = np.linspace(0, len(split) - 1, k).round() if k else np.zeros(0)
        self.ids = np.unique(spaced.astype(np.int64))
        self.of = len(split)
        self.reader = SampleReader(split)
        self.batch_size = batch_size

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
    ) -> tuple[dict, list[tuple[np.ndarray, np.ndarray]]]:
        """``{"samples", "psnr", "ssim", "seconds"}``: the means over the samples of ``model``
        (put in eval mode for the scores, then back in the mode it was in) on its device;
        and the ``(ground truth, prediction)`` display images of the first ``shown`` samples
        (for :func:`trainer.evaluate.write_grid`)."""
        t0 = time.perf_counter()
        device = next(model.parameters()).device
        training = model.training
        model.eval()
        scores, pictures = [], []
        try:
            for lo in range(0, len(self.ids), self.batch_size):
                batch = self.reader.batch(self.ids[lo : lo + self.batch_size])
                x = model_inputs(batch["maps"].to(device), roughness_channels)
                light = batch["light"].to(device, torch.float32)
                pred = model(x.contiguous(memory_format=fmt), light).float()
                target = tonemap(batch["render"].to(device))
                scores.append(torch.stack([psnr(pred, target), ssim(pred, target)], 1).cpu())
                for j in range(min(shown - len(pictures), len(pred))):
                    pictures.append((target[j].cpu().numpy(), pred[j].cpu().numpy()))
        finally:
            model.train(training)
        mean = torch.cat(scores).double().mean(0) if scores else torch.full((2,), float("nan"))
        return {
            "samples": len(self.ids),
            "psnr": round(float(mean[0]), 4),
            "ssim": round(float(mean[1]), 5),
            "seconds": round(time.perf_counter() - t0, 3),
        }, pictures
