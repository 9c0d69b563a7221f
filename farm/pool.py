"""The Ray side of the farm: the pool of render actors and the shard commit tasks (joining
Ray is :mod:`farm.cluster`).

Nothing here decides what runs where (that is :mod:`farm.scheduler`); this module creates,
answers for and kills :class:`farm.actor.RenderWorker` actors, submits tasks to them, and
starts :func:`farm.commit.commit_shard` tasks where :func:`farm.commit.placement` allows.
"""

from __future__ import annotations

import contextlib

from farm.actor import CONCURRENCY_GROUPS, RenderWorker
from farm.commit import commit_shard, placement
from farm.plan import JobConfig
from farm.state import JobState, WorkerStats, now
from render_jobs.specs import RenderSettings

#: worker statuses that may be given tasks
USABLE = ("idle", "busy")
#: how long :func:`read_errors` waits for each result of an ended task
READ_ERRORS_WAIT_S = 10.0


class WorkerPool:
    """The live Ray actors, by worker id."""

    def __init__(self, cfg: JobConfig, state: JobState, actor_cls: type = RenderWorker):
        """``actor_cls``: the actor's class (:class:`RenderWorker`; a benchmark gives a
        simulated one with the same methods)."""
        import ray

        self.ray, self.cfg, self.state = ray, cfg, state
        settings = RenderSettings(
            resolution=cfg.resolution,
            samples=cfg.samples,
            threads=cfg.cpus_per_worker,
            device="OPTIX" if cfg.gpus_per_worker else "CPU",
            texture_tiling=cfg.texture_tiling,
            denoise=cfg.denoise,
        ).to_dict()
        self.settings = settings
        self.cls = ray.remote(concurrency_groups=CONCURRENCY_GROUPS)(actor_cls).options(
            num_cpus=cfg.cpus_per_worker,
            num_gpus=cfg.gpus_per_worker,
            max_restarts=0,
            max_concurrency=1,
        )
        self.actors: dict[str, object] = {}
        self.starting: dict[object, str] = {}  # readiness ref -> worker id
        self.start_failures: list[str] = []
        self.count = 0
        self.commit_fn = ray.remote(commit_shard).options(**self._commit_options())

    def _commit_options(self) -> dict:
        # no CPU reserved: the render actors hold the CPUs, a commit is mostly compression
        # and I/O; Ray re-runs it if its process dies (farm.commit: exactly once)
        opts = {"num_cpus": 0, "max_retries": 3}
        if placement(self.cfg.out) == "driver":
            from ray.util.scheduling_strategies import NodeAffinitySchedulingStrategy

            here = self.ray.get_runtime_context().get_node_id()
            opts["scheduling_strategy"] = NodeAffinitySchedulingStrategy(here, soft=False)
        return opts

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
            self.ray.kill(actor, no_restart=True)
        self.state.workers[wid].status = status
        self.state.workers[wid].current = None

    def give_up(self, count: int) -> None:
        """Kill the ``count`` newest workers that have not answered (waiting for room, or
        still loading): they end ``unplaced``."""
        for ref, wid in list(self.starting.items())[-count:] if count else []:
            del self.starting[ref]
            self.remove(wid, "unplaced")

    def stop_all(self, wait_s: float) -> None:
        """The job is over: every actor is asked to close its Blender, all at once, and
        given ``wait_s`` seconds in all (a busy one closes only after its render), then
        killed. One that never answered (Ray found it no room, or it was still loading) is
        given up at once (:meth:`give_up`), without being waited for."""
        self.give_up(len(self.starting))
        closing = [actor.close.remote() for actor in self.actors.values()]
        with contextlib.suppress(Exception):  # dead or stuck: the kill ends it
            self.ray.wait(closing, num_returns=len(closing), timeout=wait_s)
        for wid in list(self.actors):
            self.remove(wid, "stopped")

    def usable(self) -> list[str]:
        """Workers that are placed, alive and not being removed, in start order."""
        return [w for w in self.actors if self.state.workers[w].status in USABLE]

    def submit(self, wid: str, task: dict, timeout_s: float, ticket: int) -> tuple:
        """Queue ``task`` at worker ``wid`` under ``ticket`` (unique in the job: what
        :meth:`revoke` names); returns the refs of its report and its arrays."""
        render = self.actors[wid].render.options(num_returns=2)
        return tuple(render.remote(task, timeout_s, ticket))

    def revoke(self, wid: str, ticket: int) -> None:
        """Have worker ``wid`` skip the task of ``ticket`` when it comes to it
        (:class:`farm.actor.Revocable`; answered while the worker renders). Not
        ``ray.cancel``: on Ray 2.60 a cancelled task already in an actor's queue still ran
        when the actor had no concurrency groups (docs/farm.md)."""
        actor = self.actors.get(wid)
        if actor is not None:
            actor.revoke.options(concurrency_group="control").remote(ticket)

    def screen_uv(self, wid: str, supersample: int):
        """Ask worker ``wid`` for the scene's screen UV layout; returns the result's ref."""
        return self.actors[wid].screen_uv.remote(supersample)

    def commit(self, shard: int, records: list[dict], arrays: list):
        """Start writing ``shard`` from its materials' array refs; returns the report's ref."""
        return self.commit_fn.remote(self.cfg.out, None, shard, records, *arrays)

    def lost(self, refs: list) -> list[int]:
        """Indices of ``refs`` whose objects Ray holds as lost (their node went away and they
        cannot be made again), asked without waiting: a ``get`` with no time to wait raises
        Ray's object-lost error at once for those (the owner, this process, stored it) and
        times out, with nothing deserialized here, for those on another node."""
        from ray.exceptions import GetTimeoutError

        out = []
        for i, ref in enumerate(refs):
            try:
                self.ray.get(ref, timeout=0)
            except GetTimeoutError:  # on a live node, not here: there
                pass
            except Exception:  # noqa: BLE001 - lost, or unreadable: rendered again, not trusted
                out.append(i)
        return out

    def replace(self, wid: str, status: str) -> None:
        """Remove ``wid`` (``dead`` or ``blocklisted``) and start a worker in its place."""
        if wid in self.actors:
            self.remove(wid, status)
            self.start()


def read_errors(refs, wait_s: float = READ_ERRORS_WAIT_S) -> int:
    """Read the errors that ``refs``, the results of one ended task in order, hold, so that
    Ray does not print each, traceback and all, as an "Unhandled error" when its ref goes: the
    job reports failures its own way. Returns how many it read. Stops at the first that holds
    a value: a task whose report is fine succeeded, and its arrays (megabytes) never come here.

    Each is waited for (up to ``wait_s``), not only asked for: a failed task's results reach
    this process one after another, so the arrays' copy of the error may land just after the
    report's, which is what woke the driver."""
    import ray
    from ray.exceptions import GetTimeoutError

    read = 0
    for ref in refs:
        try:
            ray.get(ref, timeout=wait_s)
        except GetTimeoutError:  # not come (a killed worker's, say): left
            return read
        except Exception:  # noqa: BLE001 - an error, now read
            read += 1
            continue
        return read
    return read
