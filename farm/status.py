"""Formatting a job state (``farm/job.json``) for people."""

from __future__ import annotations

import time
from collections import Counter

from tabulate import tabulate

from farm.state import RATE_WINDOW_S

#: worker rows ``farm status`` prints unless asked for all (a cluster job runs hundreds)
WORKER_ROWS = 20


def _ago(t: float) -> str:
    if not t:  # never (a state that did not record it)
        return "-"
    s = max(0, time.time() - t)
    return f"{s:.0f} s ago" if s < 120 else f"{s / 60:.0f} min ago"


def format_status(st: dict, worker_rows: int | None = WORKER_ROWS) -> str:
    """The job, its failures, a count of its workers by status and a table of the first
    ``worker_rows`` of them (``None``: all)."""
    return "\n".join([*_job_lines(st), *_failure_lines(st), *_worker_lines(st, worker_rows)])


def _job_lines(st: dict) -> list[str]:
    """The job's status, store, progress and shards, then whatever stands in its way."""
    done = st["frames_done"] + st["frames_skipped"]
    total = st["frames_total"]
    eta = f"{st['eta_s']:.0f} s" if st.get("eta_s") else "-"
    status = st.get("effective_status", st["status"])
    shown = status
    if status == "lost":
        shown = (
            "lost: says running, but its driver is gone (killed?); "
            "run the same `farm submit` again to resume"
        )
    rate = f"{st['frames_per_s']:.2f} frames/s"
    if status == "running" and st.get("frames_per_s_now"):  # the rate the ETA runs at
        rate += f" ({st['frames_per_s_now']:.2f} rendered in the last {RATE_WINDOW_S:.0f} s)"
    lines = [
        f"job       {shown}  (driver {st['driver']}, updated {_ago(st['updated'])})",
        f"store     {st['store']}",
        f"frames    {done}/{total} ({100 * done / total:.1f}%), {rate}, ETA {eta}",
        f"shards    {st['shards_committed']}/{st['shards_total']} committed"
        + _failed_shards(st["shards_failed"]),
    ]
    if status == "running" and st.get("cancel_requested"):
        req = st["cancel_requested"]
        lines.append(f"cancel    requested by {req['by']} {_ago(req['at'])}: the driver stops "
                     "within a few seconds")  # fmt: skip
    if st.get("stop_error"):
        lines.append(f"stopped   {st['stop_error']}")
    if st.get("screen_uv_error"):
        lines.append(
            f"screen UV layout not made: {st['screen_uv_error']} (farm screen-uv makes it)"
        )
    if status == "running" and st.get("dashboard"):
        lines.append(f"ray       {st['dashboard']} (the Ray dashboard, while the job runs)")
    return lines


def _failed_shards(shards: list[int], shown: int = 8) -> str:
    """The count of failed shards and the first ``shown`` of them, after the committed count."""
    if not shards:
        return ""
    word = "shard" if len(shards) == 1 else "shards"
    more = ", ..." if len(shards) > shown else ""
    return f", failed: {len(shards)} ({word} {', '.join(map(str, shards[:shown]))}{more})"


def _failure_lines(st: dict) -> list[str]:
    """Each material that failed (final, recovered or retrying) and each shard's failed commit."""
    if not (st["failures"] or st.get("commit_failures")):
        return []
    lines = ["failures"]
    for m, f in sorted(st["failures"].items(), key=lambda kv: int(kv[0])):
        last = f["errors"][-1] if f["errors"] else {"worker": "-", "error": "-"}
        tag = "FAILED" if f["final"] else "recovered" if f.get("recovered") else "retrying"
        lines.append(
            f"  material {m:>6}  {tag:<8} attempts {f['attempts']}  "
            f"last on {last['worker']}: {last['error']}"
        )
    for shard, error in sorted(st.get("commit_failures", {}).items(), key=lambda kv: int(kv[0])):
        lines.append(f"  shard {shard:>9}  FAILED   commit: {error}")
    return lines


def _worker_lines(st: dict, worker_rows: int | None) -> list[str]:
    """The workers counted by status, then a table of the first ``worker_rows``."""
    workers = [
        (w["worker"], w["status"], w["frames"], w["mean_frame_s"], w["failures"], w["recycled"])
        + (w.get("recalled", 0), _ago(w["last_seen"]))  # recalled: absent from older states
        for w in st["workers"].values()
    ]
    header = ["worker", "status", "frames", "s/frame", "fails", "recycled", "recalled",
              "last seen"]  # fmt: skip
    table = tabulate(workers[:worker_rows], header, floatfmt=".2f")
    lines = [_worker_counts(st["workers"].values()), table]
    if worker_rows is not None and len(workers) > worker_rows:
        lines.append(f"... {len(workers) - worker_rows} more (farm status --all-workers)")
    return lines


def _worker_counts(workers) -> str:
    """``workers   12: 8 busy, 2 idle, 2 starting`` (statuses in the order first seen)."""
    counts = Counter(w["status"] for w in workers)
    by_status = ", ".join(f"{n} {status}" for status, n in counts.items())
    return f"workers   {counts.total()}" + (f": {by_status}" if by_status else "")
