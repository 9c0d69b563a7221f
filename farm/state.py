"""The job's state, persisted with the store for people and dashboards.

``<store>/farm/job.json`` is rewritten atomically (temp + rename locally, one PUT on S3) every
couple of seconds by the driver and at the end, so ``farm status`` (and the dashboard) can show
a job while it runs and after it ends, without the driver. Shard commits stay the truth about
data: the state is a report, ``shards`` reads the store itself.
"""

from __future__ import annotations

import json
import os
import socket
import time
from dataclasses import asdict, dataclass, field

from farm.cancel import cancel_requested
from farm.lease import holder_alive, read_lease
from storage.backend import Backend

STATE_KEY = "farm/job.json"
#: progress points kept for the dashboard's frames/s chart: halved when full, so a month-long
#: job keeps its whole life at a coarser step
HISTORY_POINTS = 720


def now() -> float:
    return time.time()


@dataclass
class WorkerStats:
    worker: str
    # starting | idle | busy | dead | blocklisted | released | stopped | unplaced
    status: str = "starting"
    host: str = ""
    pid: int = 0
    nice: int = 0  # the worker's (and its Blender's) niceness: 0 unless the cluster says else
    frames: int = 0
    materials: int = 0
    frame_seconds: float = 0.0  # sum, for the mean
    failures: int = 0
    recycled: int = 0
    recalled: int = 0  # tasks taken back from its queue for an idle worker
    last_seen: float = 0.0
    current: int | None = None  # material being rendered

    @property
    def mean_frame_s(self) -> float:
        return self.frame_seconds / self.frames if self.frames else 0.0


@dataclass
class JobState:
    store: str
    settings: dict
    frames_total: int
    shards_total: int
    status: str = "running"  # running | done | failed | cancelled | interrupted
    driver: str = field(default_factory=lambda: f"{socket.gethostname()}:{os.getpid()}")
    started: float = field(default_factory=now)
    updated: float = field(default_factory=now)
    frames_done: int = 0  # in the shards this run committed
    frames_skipped: int = 0  # already committed when the job (re)started
    frames_rendered: int = 0  # in the results this run received, committed or not
    shards_committed: int = 0
    shards_failed: list[int] = field(default_factory=list)
    failures: dict[str, dict] = field(default_factory=dict)  # material -> {attempts, errors, final}
    commit_failures: dict[str, str] = field(default_factory=dict)  # shard -> error
    workers: dict[str, WorkerStats] = field(default_factory=dict)
    dashboard: str | None = None
    history: list[list[float]] = field(default_factory=list)  # add_point's points, bounded
    screen_uv_error: str | None = None  # why the store's screen UV layout could not be made
    stop_error: str | None = None  # why a failed job stopped before its end (no worker placed)

    def to_json(self) -> bytes:
        data = asdict(self)
        for w in data["workers"].values():
            w["mean_frame_s"] = w["frame_seconds"] / w["frames"] if w["frames"] else 0.0
        elapsed = max(self.updated - self.started, 1e-9)
        rate = self.frames_done / elapsed
        data["frames_per_s"] = rate
        # the time left at the rate of the last RATE_WINDOW_S: the whole run's mean lags a
        # cluster that grows (an autoscaler adding nodes) and counts the start-up
        last = len(self.history) - 1
        now_rate = window_rate(self.history, last) if last > 0 else 0.0
        data["frames_per_s_now"] = now_rate
        remaining = self.frames_total - self.frames_skipped - self.frames_done
        pace = now_rate or rate
        data["eta_s"] = remaining / pace if pace > 0 else None
        return json.dumps(data, indent=1).encode()

    def save(self, backend: Backend) -> None:
        self.updated = now()
        rendered = self.frames_rendered
        self.history = add_point(self.history, self.updated, self.frames_done, rendered)
        backend.put_atomic(STATE_KEY, self.to_json())


#: a progress point's rate (frames rendered a second) is the average over this many seconds
RATE_WINDOW_S = 30.0


def window_rate(history: list, i: int, window_s: float = RATE_WINDOW_S) -> float:
    """Frames rendered a second at ``history[i]`` (i > 0): since the latest point at least
    ``window_s`` before it (the first point, early in a job), over the time between. A
    point's last value is its frames rendered (one that did not count them has only its
    frames committed).

    Rendered, not committed: commits come a whole shard at a time, so between two points a
    few seconds apart the rate would read zero and then a shard's worth at once. The window
    smooths the steps of results as well: a result is a material, all its suns' frames."""
    t1, f1 = history[i][0], history[i][-1]
    j = i - 1
    while j > 0 and history[j][0] > t1 - window_s:
        j -= 1
    t0, f0 = history[j][0], history[j][-1]
    return max(f1 - f0, 0) / (t1 - t0) if t1 > t0 else 0.0


def add_point(
    history: list, t: float, frames: int, rendered: int | None = None, limit: int = HISTORY_POINTS
) -> list:
    """``history`` with ``[t, frames]`` (frames committed) or ``[t, frames, rendered]``
    appended; past ``limit`` points every other older point is dropped (the first and the
    newest are kept), so its size stays bounded."""
    out = [*history, [round(t, 2), frames, *([] if rendered is None else [rendered])]]
    if len(out) > limit:
        out = out[:-1:2] + [out[-1]]
    return out


def load_state(url: str, storage_options: dict | None = None) -> dict | None:
    """The job state as saved, plus ``effective_status`` (:func:`effective_status`) and, for
    a running job, ``cancel_requested``: the standing request (:mod:`farm.cancel`) or ``None``."""
    backend = Backend(url, storage_options)
    raw = backend.get(STATE_KEY)
    if raw is None:
        return None
    st = json.loads(raw)
    # only a running job's lease matters (one read fewer for the finished ones); a driver
    # ending between the two reads has let its lease go: no lease, a fresh state, "running"
    lease = read_lease(backend) if st["status"] == "running" else None
    st["effective_status"] = effective_status(st, lease, now())
    if st["effective_status"] == "running":
        st["cancel_requested"] = cancel_requested(backend)
    return st


def effective_status(st: dict, lease: dict | None, at: float) -> str:
    """The state's status, or ``lost`` when it says ``running`` but its driver is gone, by
    the lease's one rule (``farm.lease.holder_alive``): not renewed for ``LEASE_S``, or its
    driver ran on this machine and that process has ended. A state with no lease record
    beside it stands for its own: its driver and its last update."""
    if st["status"] != "running":
        return st["status"]
    return "running" if holder_alive(lease or _as_lease(st), at) else "lost"


def _as_lease(st: dict) -> dict:
    """A lease record of the state's driver (``host:pid``), renewed when it was updated."""
    host, _, pid = st.get("driver", "").rpartition(":")
    return {"host": host, "pid": int(pid) if pid.isdigit() else None, "renewed": st["updated"]}
