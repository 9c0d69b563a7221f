"""What a training run records as it goes (:class:`RunLog`): the run's config, its log lines,
TensorBoard events, held-out scores and the progress bar's postfix on rank 0, and each rank's
sample ids with ``--log-samples``. ``trainer.training.train`` makes one per rank."""

from __future__ import annotations

import hashlib
import json
import time
from pathlib import Path

import numpy as np
import torch

from storage.backend import write_atomic
from trainer import runfiles
from trainer.intervals import bracket
from trainer.scoring import write_grid
from trainer.training.config import TrainConfig
from trainer.training.trainee import Rank, Trainee
from trainer.training.validation import Validator

#: rows of ``val.png``: ground truth | network | error of the first held-out samples scored
VAL_GRID_ROWS = 3
#: the run's best held-out score so far with its per-sample PSNRs, for ``vs_best`` after a resume
BEST_SCORES = runfiles.BEST_SCORES


class RunLog:
    """What a run records as it goes. Rank 0: ``config.json``, ``log.jsonl`` (one line every
    ``log_every`` steps and at the end of each epoch, for the steps since the line before:
    their count, rank 0's mean loss, images and images/s over all ranks, data-wait share),
    TensorBoard under ``tb/`` and the progress bar's postfix; with a :attr:`validator`,
    ``val.jsonl`` (:meth:`validate`). Every rank, with ``--log-samples``:
    ``samples/rank-R.txt``, the sample ids of each step and, at the end, a hash of the final
    parameters (identical on every rank of a DDP run)."""

    def __init__(self, cfg: TrainConfig, rk: Rank, out: Path):
        self.out, self.world, self.master = out, rk.world, rk.master
        self.writer = None
        self.samples = None
        self.last_checkpoint: Path | None = None
        self.saved_at = time.monotonic()  # the last checkpoint's time, or the run's start
        self.window = _new_window()
        self.validator: Validator | None = None  # rank 0's, unless --val-samples 0
        self.val_every, self.fmt = cfg.val_every, rk.fmt
        self.last_val: dict | None = None
        #: the run's best score so far (``BEST_SCORES`` after a resume): record, per-sample PSNRs
        self.best: tuple[dict, np.ndarray] | None = None
        if rk.master:
            out.mkdir(parents=True, exist_ok=True)
            from torch.utils.tensorboard import SummaryWriter

            self.writer = SummaryWriter(str(out / runfiles.TENSORBOARD))
            (out / runfiles.CONFIG).write_text(json.dumps(cfg.to_dict(), indent=2) + "\n")
        if cfg.log_samples:
            (out / runfiles.SAMPLES).mkdir(parents=True, exist_ok=True)
            self.samples = open(out / runfiles.SAMPLES / runfiles.samples_file(rk.rank), "a")  # noqa: SIM115

    def start(self, line: str) -> None:
        if self.master:
            print(line, flush=True)

    def new_window(self) -> None:
        self.window = _new_window()

    def validation_plan(self) -> str:
        """What :meth:`validate` will score, in a line."""
        v = self.validator
        if v is None:
            return "held-out scores: off (--val-samples 0)"
        if not len(v):
            return "held-out scores: none (the run holds out no materials)"
        every = f" and every {self.val_every} steps" if self.val_every else ""
        return (
            f"held-out scores: PSNR and SSIM of {len(v)} of the {v.of} held-out samples at "
            f"each epoch's end{every} ({self.out / 'val.jsonl'})"
        )

    def validate(self, t: Trainee, bar) -> None:
        """Score the network on the held-out samples (:mod:`trainer.training.validation`), once a
        step: a line in ``val.jsonl``, TensorBoard's ``val/psnr`` and ``val/ssim``, a line
        above the bar, and ``val.png``, the grid ``trainer eval`` draws of the first
        :data:`VAL_GRID_ROWS` samples (replaced whole). ``heldout_set`` names the samples
        scored (:func:`trainer.training.validation.samples_digest`), so that runs' scores are
        compared only where they score the same samples. A run with a moving average scores
        the average (what its checkpoints render with) and the trained weights
        (``trained_psnr``, ``trained_ssim``; TensorBoard's ``val/trained_psnr`` and
        ``val/trained_ssim``). Each record has the PSNR's interval over the materials and,
        after the run's first score, ``vs_best``: the PSNR less that of the best score before
        it, on the same samples, with its interval
        (:meth:`trainer.training.validation.Validator.against`); the best's per-sample scores are
        kept in ``val-best.json`` for a resumed run. Its time is left out of the window's images/s.
        Rank 0 only."""
        v = self.validator
        if v is None or not len(v) or (self.last_val or {}).get("step") == t.step:
            return
        t0 = time.perf_counter()
        others = {} if t.ema is None else {"trained": t.model}
        scores, shown, each = v.score(
            t.rendering, t.model_cfg.roughness_channels, t.tonemap, self.fmt, VAL_GRID_ROWS, others
        )
        write_grid(self.out / runfiles.VAL_GRID, shown)
        self.window["t"] += time.perf_counter() - t0
        rec = {"step": t.step, "epoch": t.epoch, **scores, "heldout_set": v.digest}
        best = self.best_before(v.digest, len(each))
        if best is not None:
            rec["vs_best"] = {"step": best[0]["step"], **v.against(best[1], each)}
        if best is None or rec["psnr"] > best[0]["psnr"]:
            self.best = (rec, each)
            keep = {"step": rec["step"], "psnr": rec["psnr"], "heldout_set": v.digest}
            text = json.dumps({**keep, "psnr_each": [float(x) for x in each]})
            write_atomic(self.out / BEST_SCORES, lambda f: f.write(text.encode()))
        rec["time"] = round(time.time(), 3)
        with open(self.out / runfiles.VAL, "a") as f:
            f.write(json.dumps(rec) + "\n")
        for key in (k for k in scores if k.endswith(("psnr", "ssim"))):
            self.writer.add_scalar(f"val/{key}", scores[key], t.step)
        trained = f" (trained weights {rec['trained_psnr']:.2f} dB)" if others else ""
        bar.write(_score_line(rec, trained))
        self.last_val = rec

    def best_before(self, digest: str, n: int) -> tuple[dict, np.ndarray] | None:
        """The run's best score so far, read from ``BEST_SCORES`` when this process has none
        (a resumed run), if it scored the same ``n`` samples (``digest``)."""
        if self.best is None and (self.out / BEST_SCORES).exists():
            kept = json.loads((self.out / BEST_SCORES).read_text())
            self.best = kept, np.asarray(kept.pop("psnr_each"), dtype=np.float64)
        if self.best is None or self.best[0]["heldout_set"] != digest or len(self.best[1]) != n:
            return None
        return self.best

    def record(self, t: Trainee, batch: dict, loss: torch.Tensor, waited: float, bar) -> None:
        """One step done: add it to the window, note its samples, move the bar."""
        n = len(batch["id"])
        self.window["wait"] += waited
        self.window["images"] += n
        self.window["loss"] += loss
        self.window["lr"] = t.opt.param_groups[0]["lr"]
        self.window["n"] += 1
        if self.samples is not None:
            ids = ",".join(str(int(i)) for i in batch["id"])
            self.samples.write(f"{t.epoch} {t.step} {ids}\n")
        bar.update(1)

    def flush(self, t: Trainee, bar) -> None:
        """Write the window's log line (rank 0) and start a new window."""
        if self.master:
            _log(self.out, self.writer, bar, t.step, t.epoch, self.window, self.world)
        self.new_window()

    def close(self, model: torch.nn.Module) -> None:
        if self.samples is not None:
            blob = b"".join(p.detach().cpu().numpy().tobytes() for p in model.parameters())
            self.samples.write(f"params {hashlib.sha256(blob).hexdigest()}\n")
            self.samples.close()
        if self.writer is not None:
            self.writer.close()


def _score_line(rec: dict, trained: str) -> str:
    """A held-out score as the run prints it, with its intervals where it has them."""
    ci = f" {bracket(rec['psnr_low'], rec['psnr_high'])}" if rec["psnr_low"] is not None else ""
    line = (
        f"step {rec['step']}: held-out PSNR {rec['psnr']:.2f} dB{ci} over "
        f"{rec['materials']} material{'s' if rec['materials'] != 1 else ''}, "
        f"SSIM {rec['ssim']:.4f}{trained} "
        f"({rec['samples']} samples, {rec['seconds']:.1f} s)"
    )
    if d := rec.get("vs_best"):
        ci = bracket(d["low"], d["high"], "+.2f")
        line += f"; {d['mean']:+.2f} dB {ci} on the best before it (step {d['step']})"
    return line


def _new_window() -> dict:
    """Running totals between two log lines."""
    return {"t": time.perf_counter(), "wait": 0.0, "images": 0, "loss": 0.0, "n": 0}


def _log(out: Path, writer, bar, step: int, epoch: int, window: dict, world: int) -> None:
    """One log line (rank 0's loss; throughput over all ranks), TensorBoard and the bar."""
    dt = max(time.perf_counter() - window["t"], 1e-9)
    rec = {
        "step": step,
        "epoch": epoch,
        "steps": window["n"],
        "images": window["images"] * world,
        "loss": round(float(window["loss"]) / max(window["n"], 1), 6),
        "images_per_second": round(window["images"] * world / dt, 2),
        "data_wait": round(window["wait"] / dt, 4),
        "lr": float(f"{window['lr']:.6g}"),  # the last step's
        "time": round(time.time(), 3),
    }
    with open(out / runfiles.LOG, "a") as f:
        f.write(json.dumps(rec) + "\n")
    for k in ("loss", "images_per_second", "data_wait", "lr"):
        writer.add_scalar(f"train/{k}", rec[k], step)
    bar.set_postfix(
        loss=rec["loss"], img_s=rec["images_per_second"], wait=f"{rec['data_wait']:.0%}"
    )
