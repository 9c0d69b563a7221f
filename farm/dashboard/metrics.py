"""``/metrics``: the farm's jobs and the trainer's runs in the Prometheus text format.

Names follow Prometheus conventions: a ``shaderball_`` prefix, base units (seconds),
``_total`` for counters; labels are few and bounded (``store``, ``run``, a worker
``status``), never a material. Values are read at scrape time from what the farm and trainer
persist (:mod:`farm.dashboard.jobs`, :mod:`farm.dashboard.runs`).

=============================================  ====================================================
``shaderball_farm_frames_committed_total``     frames in committed shards (resumed ones included)
``shaderball_farm_frames_rendered_total``      frames in the results the driver received this run
``shaderball_farm_frames_planned``             frames in the dataset
``shaderball_farm_failures_total``             failed render attempts
``shaderball_farm_materials_failed``           materials that failed for good
``shaderball_farm_workers{status}``            workers by status (idle, busy, dead, ...)
``shaderball_farm_shards_committed_total``     committed shards
``shaderball_farm_eta_seconds``                the running job's estimated time left
``shaderball_farm_frame_seconds``              histogram of committed frames' render times
``shaderball_farm_job_running``                1 while the job runs
``shaderball_train_step``                      the run's last logged step
``shaderball_train_loss``                      its loss
``shaderball_train_images_per_second``         its throughput
``shaderball_train_data_wait_ratio``           its share of time waiting for data
``shaderball_train_val_psnr_db``               its held-out PSNR at the last score (``val.jsonl``)
``shaderball_train_val_psnr_low_db``           the 95 % interval's bounds around it (5 or more
``shaderball_train_val_psnr_high_db``          held-out materials: :mod:`trainer.intervals`)
``shaderball_train_val_ssim``                  its held-out SSIM at the last score
``shaderball_train_val_trained_psnr_db``       with a moving average: the trained weights' PSNR
=============================================  ====================================================
"""

from __future__ import annotations

import collections

import numpy as np
from prometheus_client.core import (
    CounterMetricFamily,
    GaugeMetricFamily,
    HistogramMetricFamily,
)

FRAME_BUCKETS = (0.1, 0.25, 0.5, 1, 2.5, 5, 10, 30, 60, 120, 300, 600)


def frame_histogram(seconds: np.ndarray) -> tuple[list[tuple[str, float]], float]:
    """Cumulative Prometheus buckets of ``seconds`` and their sum."""
    buckets = [(str(b), float(np.sum(seconds <= b))) for b in FRAME_BUCKETS]
    buckets.append(("+Inf", float(len(seconds))))
    return buckets, float(np.sum(seconds))


class Collector:
    """Reads job rows and run summaries at each scrape (``jobs()``, ``runs()`` callables)."""

    def __init__(self, jobs, runs, frame_seconds):
        self.jobs, self.runs, self.frame_seconds = jobs, runs, frame_seconds

    def collect(self):
        yield from self._farm_families()
        yield from self._train_families()

    def _farm_families(self):
        """The farm's families, a sample for each readable store."""
        f = "shaderball_farm_"
        committed = CounterMetricFamily(f + "frames_committed", "Frames in committed shards",
                                        labels=["store"])  # fmt: skip
        planned = GaugeMetricFamily(f + "frames_planned", "Frames in the dataset", labels=["store"])
        rendered = CounterMetricFamily(f + "frames_rendered",
                                       "Frames in the render results the driver received",
                                       labels=["store"])  # fmt: skip
        failures = CounterMetricFamily(f + "failures", "Failed render attempts", labels=["store"])
        final = GaugeMetricFamily(f + "materials_failed", "Materials failed for good",
                                  labels=["store"])  # fmt: skip
        workers = GaugeMetricFamily(f + "workers", "Workers by status", labels=["store", "status"])
        shards = CounterMetricFamily(f + "shards_committed", "Committed shards", labels=["store"])
        eta = GaugeMetricFamily(f + "eta_seconds", "Estimated time left", labels=["store"])
        running = GaugeMetricFamily(f + "job_running", "1 while the job runs", labels=["store"])
        hist = HistogramMetricFamily(f + "frame_seconds", "Render time of committed frames",
                                     labels=["store"], unit="")  # fmt: skip
        for row in self.jobs():
            if row.get("error"):
                continue
            name = row["label"]
            planned.add_metric([name], row["frames_total"])
            committed.add_metric([name], row["frames_done"])
            running.add_metric([name], 1.0 if row["status"] == "running" else 0.0)
            st = row.get("state")
            if st is not None:
                failures.add_metric([name], sum(x["attempts"] for x in st["failures"].values()))
                final.add_metric([name], row["failed"])
                shards.add_metric([name], st["shards_committed"])
                if "frames_rendered" in st:  # a job state an older version wrote lacks it
                    rendered.add_metric([name], st["frames_rendered"])
                by = collections.Counter(w["status"] for w in st["workers"].values())
                for status, n in sorted(by.items()):
                    workers.add_metric([name, status], n)
                if row["eta_s"] is not None:
                    eta.add_metric([name], row["eta_s"])
            seconds = self.frame_seconds(row)
            if seconds is not None:
                buckets, total = frame_histogram(seconds)
                hist.add_metric([name], buckets, total)
        yield from (committed, rendered, planned, failures, final, workers, shards, eta, running)
        yield hist

    def _train_families(self):
        """The trainer's families, a sample for each run with a logged step or score."""
        t = "shaderball_train_"
        step = GaugeMetricFamily(t + "step", "Last logged step", labels=["run"])
        loss = GaugeMetricFamily(t + "loss", "Loss at the last logged step", labels=["run"])
        ips = GaugeMetricFamily(t + "images_per_second", "Training throughput", labels=["run"])
        wait = GaugeMetricFamily(t + "data_wait_ratio", "Share of time waiting for data",
                                 labels=["run"])  # fmt: skip
        vpsnr = GaugeMetricFamily(t + "val_psnr_db", "Held-out PSNR at the last score",
                                  labels=["run"])  # fmt: skip
        vlow, vhigh = (GaugeMetricFamily(t + f"val_psnr_{b}_db",
                                         f"The {b} bound of the held-out PSNR's 95 % interval",
                                         labels=["run"]) for b in ("low", "high"))  # fmt: skip
        vssim = GaugeMetricFamily(t + "val_ssim", "Held-out SSIM at the last score",
                                  labels=["run"])  # fmt: skip
        vtrained = GaugeMetricFamily(t + "val_trained_psnr_db",
                                     "Held-out PSNR of the trained weights beside the average",
                                     labels=["run"])  # fmt: skip
        for run in self.runs():
            last = run["val_last"]
            if last is not None:
                vpsnr.add_metric([run["label"]], last["psnr"])
                vssim.add_metric([run["label"]], last["ssim"])
                if "psnr_low" in last:
                    vlow.add_metric([run["label"]], last["psnr_low"])
                    vhigh.add_metric([run["label"]], last["psnr_high"])
                if "trained_psnr" in last:
                    vtrained.add_metric([run["label"]], last["trained_psnr"])
            if run["step"] is None:
                continue
            step.add_metric([run["label"]], run["step"])
            loss.add_metric([run["label"]], run["loss"])
            ips.add_metric([run["label"]], run["images_per_second"])
            wait.add_metric([run["label"]], run["data_wait"])
        yield from (step, loss, ips, wait, vpsnr, vlow, vhigh, vssim, vtrained)
