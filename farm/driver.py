"""The farm driver: plan, start Ray workers, hand out tasks, retry, commit shards, report.

Failure handling is the driver's own, not Ray's task retries, because it needs what Ray's
retries do not give: a retry on *another* worker, exponential backoff, the error of every
attempt kept for the report, and per-worker failure counts. A task that raises (Blender error,
unreadable texture, per-sun timeout in the worker) or whose worker dies (SIGKILL, node lost)
is retried up to ``max_attempts`` times with backoff ``backoff_s * 2**(attempt-1)``, on a worker
that has not failed it where one exists; then it is recorded as failed and its shard is left
uncommitted (a resubmit renders it again). A worker that fails ``blocklist_after`` tasks is
blocklisted (killed) and replaced; a dead worker is replaced. A task running longer than
``task_timeout_s x (suns + 1)`` has its worker killed (a failure, reported as a timeout).

Backpressure: each worker holds one task; results wait in the driver only until their shard is
complete and written, and tasks are handed out in shard order, so driver memory is bounded by
the workers, not the job. Resume: committed shards are skipped.
"""

from __future__ import annotations

import collections
import contextlib
import os
import sys
import time
from dataclasses import dataclass

from tqdm import tqdm

from farm.plan import JobConfig, layout_for, material_specs, task_for
from farm.state import JobState, WorkerStats, now
from farm.worker import RenderWorker
from render_jobs.errors import MaterialError
from render_jobs.materials import load_maps
from render_jobs.specs import RenderSettings
from storage.convert import payload_from_packed
from storage.writer import create_store, write_shard

STATE_EVERY_S = 2.0
#: tasks a worker may hold: the next waits in its actor's queue, so it never idles while the
#: driver handles a result (the second is only given while the queue outnumbers the workers)
PIPELINE = 2


class FarmError(RuntimeError):
    """The job could not start (bad input, incompatible store, no Ray)."""


@dataclass
class Summary:
    store: str
    frames_total: int
    frames_rendered: int
    frames_skipped: int
    failed_materials: dict[int, str]
    failed_shards: list[int]
    wall_s: float
    dashboard: str | None
    startup_s: float
    render_end_s: float  # from the start to the last result (before workers and Ray stop)

    @property
    def ok(self) -> bool:
        return not self.failed_materials


def validate(cfg: JobConfig, progress: bool = True):
    """Specs of every material, with every file-based one loaded and checked (nothing starts
    on bad input)."""
    specs = material_specs(cfg)
    files = [s for s in specs if s.kind == "svbrdf"]
    for spec in tqdm(
        files,
        desc="validating",
        unit="material",
        disable=not progress or not files,
        file=sys.stderr,
    ):
        load_maps(spec)
    return specs


def _is_loopback(address: str | None) -> bool:
    if not address:
        return True  # the embedded Ray
    host = address.split("://")[-1].rsplit(":", 1)[0]
    return host in ("localhost", "::1") or host.startswith("127.")


def _keep_ray_on_loopback(address: str | None) -> None:
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


class _Pool:
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


def submit(cfg: JobConfig, progress: bool = True, echo=print) -> Summary:
    """Run (or resume) the job ``cfg`` to the end; see the module docstring."""
    t_start = time.perf_counter()
    _keep_ray_on_loopback(cfg.address)
    try:
        specs = validate(cfg, progress)
    except MaterialError as exc:
        raise FarmError(str(exc)) from None
    layout = layout_for(cfg, len(specs))
    settings = cfg.dataset_settings()
    from storage.errors import StoreError

    try:
        store = create_store(cfg.out, layout, settings, exist_ok=True)
    except StoreError as exc:
        raise FarmError(f"{exc} (use another --out, or the original settings to resume)") from None
    committed = set(store.committed_shards())
    todo = [s for s in range(layout.num_shards) if s not in committed]
    state = JobState(
        store=cfg.out,
        settings=settings,
        frames_total=layout.num_samples,
        shards_total=layout.num_shards,
        shards_committed=len(committed),
    )
    state.frames_skipped = sum(len(layout.shard_samples(s)) for s in committed)
    if committed:
        echo(f"resuming: {len(committed)} of {layout.num_shards} shards already committed")
    if not todo:  # keep the finished job's state as it is
        return Summary(
            cfg.out, layout.num_samples, 0, state.frames_skipped, {}, [], 0.0, None, 0.0, 0.0
        )

    import ray
    from ray.exceptions import RayActorError, RayTaskError

    state.dashboard = connect(cfg.address, cfg.ray_dashboard)
    echo(f"ray dashboard: {state.dashboard or 'off'}")
    workers = cfg.workers or max(
        1, int(ray.cluster_resources().get("CPU", 1)) // cfg.cpus_per_worker
    )
    pool = _Pool(cfg, state)
    first = {pool.start() for _ in range(workers)}
    startup = None  # until the first workers answer: Ray start + Blender scene builds

    queue = collections.deque(m for s in todo for m in layout.shard_materials(s))
    not_before: dict[int, float] = {}
    attempts: collections.Counter[int] = collections.Counter()
    failed_on: dict[int, set[str]] = {}
    errors: dict[int, list[dict]] = collections.defaultdict(list)
    failed: dict[int, str] = {}
    buffer: dict[int, dict[int, dict]] = collections.defaultdict(dict)
    dead_shards: set[int] = set()
    inflight: dict[object, tuple[str, int, float]] = {}
    timed_out: set[object] = set()
    # the worker enforces the timeout per sun; this guards against a worker stuck elsewhere
    guard = cfg.task_timeout_s * (cfg.suns + 1)
    last_live = now()
    remaining = sum(len(layout.shard_samples(s)) for s in todo)
    bar = tqdm(
        total=remaining,
        desc="frames",
        unit="frame",
        disable=not progress,
        file=sys.stderr,
        smoothing=0.1,
    )
    last_save = 0.0

    def fail(m: int, wid: str, error: str) -> None:
        attempts[m] += 1
        failed_on.setdefault(m, set()).add(wid)
        errors[m].append({"worker": wid, "error": error, "at": now()})
        w = state.workers[wid]
        w.failures += 1
        final = attempts[m] >= cfg.max_attempts
        state.failures[str(m)] = {"attempts": attempts[m], "errors": errors[m][-5:], "final": final}
        if final:
            failed[m] = error
            shard = m // layout.materials_per_shard
            dead_shards.add(shard)
            buffer.pop(shard, None)
            state.shards_failed = sorted(dead_shards)
        else:
            not_before[m] = now() + cfg.backoff_s * 2 ** (attempts[m] - 1)
            queue.append(m)
        if w.failures >= cfg.blocklist_after and wid in pool.actors:
            release_queued(wid)
            pool.remove(wid, "blocklisted")
            pool.start()
        bar.set_postfix(
            shards=f"{state.shards_committed}/{layout.num_shards}",
            failures=sum(attempts.values()),
            refresh=False,
        )

    def release_queued(wid: str, keep=None) -> None:
        """Put the tasks still queued at a worker being removed back in the queue, uncounted:
        they never started there (``keep``: a ref that stays, to fail on its own)."""
        for r, (q, m, _) in list(inflight.items()):
            if q == wid and r is not keep:
                inflight.pop(r)
                queue.appendleft(m)

    def done(m: int, wid: str, res: dict) -> None:
        w = state.workers[wid]
        w.frames += len(res["seconds"])
        w.materials += 1
        w.frame_seconds += float(sum(res["seconds"]))
        w.recycled += int(res["recycled"])
        w.host, w.pid = res["host"], res["pid"]
        bar.update(len(res["seconds"]))  # rendered; state.frames_done counts committed ones
        shard = m // layout.materials_per_shard
        if str(m) in state.failures:  # an earlier failure was retried successfully
            state.failures[str(m)]["recovered"] = True
        if shard in dead_shards:
            return
        buffer[shard][m] = res
        if len(buffer[shard]) == len(layout.shard_materials(shard)):
            results = buffer.pop(shard)
            records = [
                {"kind": specs[i].kind, "source_id": specs[i].source_id, "spec": specs[i].to_dict()}
                for i in layout.shard_materials(shard)
            ]
            packed = [results[i] for i in layout.shard_materials(shard)]
            write_shard(store, shard, payload_from_packed(layout, shard, packed, records))
            state.shards_committed += 1
            state.frames_done += len(layout.shard_samples(shard))
            bar.set_postfix(
                shards=f"{state.shards_committed}/{layout.num_shards}",
                failures=sum(attempts.values()),
                refresh=False,
            )

    try:
        while queue or inflight:
            t = now()
            load = collections.Counter(wid for wid, _, _ in inflight.values())
            usable = [w for w in pool.actors if state.workers[w].status in ("idle", "busy")]
            depth = PIPELINE if len(queue) > len(usable) else 1
            free = [w for k in range(depth) for w in usable if load[w] <= k]  # one each first
            for wid in free:
                if state.workers[wid].status not in ("idle", "busy"):
                    continue  # blocklisted or gone since the list was made
                pick = None
                for m in queue:
                    if not_before.get(m, 0) > t:
                        continue
                    tried = failed_on.get(m, ())
                    # prefer a worker that has not failed m, unless every live one has
                    if wid not in tried or all(w in tried for w in pool.actors):
                        pick = m
                        break
                if pick is None:
                    continue
                queue.remove(pick)
                ref = pool.actors[wid].render.remote(
                    task_for(cfg, pick, specs[pick]).to_dict(), cfg.task_timeout_s
                )
                inflight[ref] = (wid, pick, t)
                if state.workers[wid].status == "idle":
                    state.workers[wid].status, state.workers[wid].current = "busy", pick
            waiting = list(inflight) + list(pool.starting)
            ready, _ = ray.wait(waiting, num_returns=1, timeout=0.25) if waiting else ([], [])
            if not waiting:
                time.sleep(0.05)
            live = [w for w in pool.actors if state.workers[w].status in ("idle", "busy")]
            if live or inflight:
                last_live = now()
            elif now() - last_live > cfg.placement_timeout_s:
                why = "; ".join(pool.start_failures[-3:]) or (
                    f"Ray could not place a worker needing {cfg.cpus_per_worker} CPU(s) and "
                    f"{cfg.gpus_per_worker} GPU(s)"
                )
                raise FarmError(f"no live worker for {cfg.placement_timeout_s:.0f} s: {why}")
            for ref in ready:
                if ref in pool.starting:
                    pool.ready(ref)
                    if startup is None and first.isdisjoint(pool.starting.values()):
                        startup = time.perf_counter() - t_start
                    continue
                wid, m, started = inflight.pop(ref)
                w = state.workers[wid]
                w.last_seen, w.current = now(), None
                queued = [r for r, (q, _, _) in inflight.items() if q == wid]
                for r in queued[:1]:  # the worker starts its queued task now: time it from here
                    inflight[r] = (wid, inflight[r][1], now())
                    w.current = inflight[r][1]
                try:
                    res = ray.get(ref)
                except RayActorError as exc:
                    if wid in pool.actors:  # died under us: replace it
                        release_queued(wid)
                        pool.remove(wid, "dead")
                        pool.start()
                    if ref in timed_out:
                        timed_out.discard(ref)
                        fail(m, wid, f"timed out after {now() - started:.0f} s (worker killed)")
                    else:
                        fail(m, wid, f"worker died: {type(exc).__name__}")
                    continue
                except RayTaskError as exc:
                    cause = exc.cause if getattr(exc, "cause", None) else exc
                    if w.status == "busy" and not queued:
                        w.status = "idle"
                    fail(m, wid, f"{type(cause).__name__}: {str(cause).splitlines()[0]}")
                    continue
                if not queued:
                    w.status = "idle"
                done(m, wid, res)
            for ref, (wid, _m, started) in list(inflight.items()):
                if now() - started > guard and wid in pool.actors:
                    timed_out.add(ref)
                    release_queued(wid, keep=ref)
                    pool.remove(wid, "dead")  # its ref now fails with RayActorError
                    pool.start()
            if now() - last_save > STATE_EVERY_S:
                state.save(store.backend)
                last_save = now()
        state.status = "failed" if failed else "done"
        render_end = time.perf_counter() - t_start
    except BaseException:
        state.status = "interrupted"
        raise
    finally:
        bar.close()
        for wid in list(pool.actors):
            pool.remove(wid, "stopped")
        state.save(store.backend)
        ray.shutdown()
    return Summary(
        store=cfg.out,
        frames_total=layout.num_samples,
        frames_rendered=state.frames_done,
        frames_skipped=state.frames_skipped,
        failed_materials=failed,
        failed_shards=sorted(dead_shards),
        wall_s=time.perf_counter() - t_start,
        dashboard=state.dashboard,
        startup_s=startup if startup is not None else time.perf_counter() - t_start,
        render_end_s=render_end,
    )
