"""The Ray side of the farm: joining or starting Ray, and the pool of render actors.

Nothing here decides what runs where (that is :mod:`farm.scheduler`); this module creates,
answers for and kills :class:`farm.actor.RenderWorker` actors and submits tasks to them.
"""

from __future__ import annotations

import contextlib
import os
import sys

from farm.actor import RenderWorker
from farm.plan import JobConfig
from farm.state import JobState, WorkerStats, now
from render_jobs.specs import RenderSettings

#: worker statuses that may be given tasks
USABLE = ("idle", "busy")


def _is_loopback(address: str | None) -> bool:
    if not address:
        return True  # the embedded Ray
    host = address.split("://")[-1].rsplit(":", 1)[0]
    return host in ("localhost", "::1") or host.startswith("127.")


def keep_ray_on_loopback(address: str | None) -> None:
    """For the embedded Ray and clusters on 127.0.0.1: Ray on Linux rewrites a loopback
    address to the machine's outward IP unless this is set before ``ray`` is imported."""
    if _is_loopback(address or os.environ.get("RAY_ADDRESS")) and "ray" not in sys.modules:
        os.environ.setdefault("RAY_ENABLE_WINDOWS_OR_OSX_CLUSTER", "0")


def connect(address: str | None, dashboard: bool = True) -> str | None:
    """Join the Ray cluster at ``address`` (or ``RAY_ADDRESS``), else start an embedded one
    (with its dashboard unless ``dashboard`` is false). Returns the dashboard URL."""
    import ray

    address = address or os.environ.get("RAY_ADDRESS") or None
    if address:
        extra = {"_node_ip_address": "127.0.0.1"} if _is_loopback(address) else {}
        ctx = ray.init(address=address, log_to_driver=False, **extra)
    else:
        ctx = ray.init(  # embedded: everything on the loopback interface
            num_cpus=os.cpu_count(),
            include_dashboard=dashboard,
            log_to_driver=False,
            _node_ip_address="127.0.0.1",
            dashboard_host="127.0.0.1",
            # Ray runs its workers at nice 15 by default; here the renders are the work
            _system_config={"worker_niceness": 0},
        )
    url = getattr(ctx, "dashboard_url", None)
    return f"http://{url}" if url and not url.startswith("http") else url


class WorkerPool:
    """The live Ray actors, by worker id."""

    def __init__(self, cfg: JobConfig, state: JobState):
        import ray

        self.ray, self.cfg, self.state = ray, cfg, state
        settings = RenderSettings(
            resolution=cfg.resolution,
            samples=cfg.samples,
            threads=cfg.cpus_per_worker,
            device="OPTIX" if cfg.gpus_per_worker else "CPU",
            texture_tiling=cfg.texture_tiling,
        ).to_dict()
        self.settings = settings
        self.cls = ray.remote(RenderWorker).options(
            num_cpus=cfg.cpus_per_worker,
            num_gpus=cfg.gpus_per_worker,
            max_restarts=0,
            max_concurrency=1,
        )
        self.actors: dict[str, object] = {}
        self.starting: dict[object, str] = {}  # readiness ref -> worker id
        self.start_failures: list[str] = []
        self.count = 0

    def start(self) -> str:
        """Create a worker; it gets tasks once Ray has placed it and it answers (``ready``)."""
        wid = f"w{self.count}"
        self.count += 1
        actor = self.cls.remote(wid, self.settings, self.cfg.recycle_after, self.cfg.rss_limit_mb)
        self.actors[wid] = actor
        self.starting[actor.info.remote()] = wid
        self.state.workers[wid] = WorkerStats(worker=wid, status="starting", last_seen=now())
        return wid

    def ready(self, ref) -> None:
        """A worker answered: it is placed and alive."""
        wid = self.starting.pop(ref)
        w = self.state.workers[wid]
        try:
            info = self.ray.get(ref)
        except Exception as exc:  # noqa: BLE001 - any start-up failure: the worker is gone
            self.actors.pop(wid, None)
            w.status, w.current = "dead", None
            self.start_failures.append(f"{wid}: {type(exc).__name__}: {exc}".splitlines()[0])
            return
        if wid in self.actors:
            w.status, w.host, w.pid, w.last_seen = "idle", info["host"], info["pid"], now()
            w.nice = info["nice"]

    def remove(self, wid: str, status: str) -> None:
        actor = self.actors.pop(wid, None)
        if actor is not None:
            if status == "stopped":  # the job is over: let it close its Blender first
                with contextlib.suppress(Exception):  # dead or stuck: the kill ends it
                    self.ray.get(actor.close.remote(), timeout=15)
            self.ray.kill(actor, no_restart=True)
        self.state.workers[wid].status = status
        self.state.workers[wid].current = None

    def usable(self) -> list[str]:
        """Workers that are placed, alive and not being removed, in start order."""
        return [w for w in self.actors if self.state.workers[w].status in USABLE]

    def submit(self, wid: str, task: dict, timeout_s: float):
        """Queue ``task`` at worker ``wid``; returns its result ref."""
        return self.actors[wid].render.remote(task, timeout_s)

    def replace(self, wid: str, status: str) -> None:
        """Remove ``wid`` (``dead`` or ``blocklisted``) and start a worker in its place."""
        if wid in self.actors:
            self.remove(wid, status)
            self.start()
