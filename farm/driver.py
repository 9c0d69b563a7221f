"""The farm driver: plan, start Ray workers, hand out tasks, have shards committed, report.

Its parts, each its own module: :mod:`farm.scheduler` decides what each worker gets, when a
failed task is retried and where, when a worker is blocklisted and when a task has timed out
(pure policy, tested with a fake clock); :mod:`farm.pool` starts, answers for and kills the Ray
actors; :mod:`farm.assembly` keeps the refs of results until their shard is whole;
:mod:`farm.commit` writes a whole shard as a Ray task near its data, so no render's bytes pass
through this process. This module is the loop between them: dispatch, wait for one Ray event,
feed it to the scheduler, start commits (at most ``max(2, workers // 8)`` at once), persist
the job state.

Failure handling is the driver's own, not Ray's task retries, because it needs what Ray's
retries do not give: a retry on *another* worker, exponential backoff, the error of every
attempt kept for the report, and per-worker failure counts. A task whose failures reach
``max_attempts`` leaves its shard uncommitted (a resubmit renders it again). A worker running
one task longer than ``task_timeout_s x (suns + 1)`` is killed (the worker itself enforces the
timeout per sun; this guards against one stuck elsewhere). A commit whose results were lost
(their node went away first) sends the materials whose results Ray holds as lost back to the
queue, and the shard's other results wait for them again; one that fails otherwise leaves
the shard uncommitted and is reported. Resume: committed shards are skipped.
One driver at a time: :mod:`farm.lease`.
"""

from __future__ import annotations

import collections
import logging
import time
from dataclasses import dataclass, field
from typing import NamedTuple

from farm import sizing
from farm.actor import RenderWorker
from farm.assembly import ShardAssembly
from farm.cancel import cancel_requested, clear_cancel
from farm.cluster import address_in_force, check_cluster, connect, ray_environment
from farm.lease import Lease, LeaseHeld, acquire
from farm.plan import JobConfig, layout_for, material_specs, task_for
from farm.pool import WorkerPool, read_errors
from farm.scheduler import Scheduler, awaited
from farm.state import JobState, now
from farm.validate import pending, read_all
from render_jobs.errors import MaterialError
from render_jobs.screen_uv import FILE as SCREEN_UV_FILE
from render_jobs.screen_uv import default_supersample
from shaderball.errors import UserError
from shaderball.progress import bar as progress_bar
from shaderball.signals import sigterm_held, stop_on_sigterm
from storage.backend import Backend
from storage.errors import StoreError
from storage.writer import create_store, put_screen_uv

log = logging.getLogger("shaderball.farm")
STATE_EVERY_S = 2.0
#: workers asked for the store's screen UV layout before the job goes on without it
SCREEN_UV_TRIES = 3
#: tasks a worker may hold (:mod:`farm.scheduler`, pipelining)
PIPELINE = 2
#: how often a job looks at its workers against the cluster and the queue (:mod:`farm.sizing`)
RESIZE_EVERY_S = 5.0


def commit_slots(workers: int) -> int:
    """Commits that may run at once for a job of ``workers`` workers."""
    return max(2, workers // 8)


class FarmError(UserError, RuntimeError):
    """The job could not start (bad input, incompatible store, no Ray)."""


class InFlight(NamedTuple):
    """A task handed to a worker: the worker, the material, the ref of its arrays, and the
    ticket it went with (what a revocation names)."""

    worker: str
    material: int
    arrays: object
    ticket: int


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
    failed_commits: dict[int, str] = field(default_factory=dict)  # shard -> error
    cancelled: bool = False  # stopped by farm cancel; the same command resumes
    failed_attempts: int = 0  # every failed try, the retried ones included

    @property
    def ok(self) -> bool:
        return not self.failed_materials and not self.failed_commits


def validate(cfg: JobConfig, progress: bool = True):
    """Specs of every material, with every file-based one still to render loaded and checked
    (nothing starts on bad input), in parallel (:mod:`farm.validate`)."""
    specs = material_specs(cfg)
    files = [i for i, spec in enumerate(specs) if spec.kind == "svbrdf"]
    if files:  # else the store need not be opened
        todo = set(pending(cfg, layout_for(cfg, len(specs))))
        read_all([specs[i] for i in files if i in todo], progress)
    return specs


@dataclass
class Job:
    """What a job renders and where: its specs, the store's layout, the store, the shards to do."""

    cfg: JobConfig
    specs: list
    layout: object
    store: object
    todo: list[int]
    state: JobState
    needs_screen_uv: bool = False  # the store has no screen UV layout yet


def prepare(cfg: JobConfig, specs: list, echo) -> Job:
    """Create (or reopen, to resume) the store and see what is left to render."""
    layout = layout_for(cfg, len(specs))
    settings = cfg.dataset_settings()
    try:
        store = create_store(cfg.out, layout, settings, exist_ok=True)
    except StoreError as exc:
        raise FarmError(f"{exc} (use another --out, or the original settings to resume)") from None
    committed = set(store.committed_shards())
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
    todo = [s for s in range(layout.num_shards) if s not in committed]
    needs_uv = store.backend.size(SCREEN_UV_FILE) is None
    return Job(cfg, specs, layout, store, todo, state, needs_uv)


def submit(
    cfg: JobConfig, progress: bool = True, echo=print, actor_cls: type = RenderWorker
) -> Summary:
    """Run (or resume) the job ``cfg`` to the end; see the module docstring. ``actor_cls``:
    the render actor (a benchmark's simulated one; :class:`farm.pool.WorkerPool`)."""
    t_start = time.perf_counter()
    stop_on_sigterm()
    ray_environment(cfg.address)
    try:
        specs = validate(cfg, progress)  # nothing is written on bad input
        node = check_cluster(cfg.address)  # nor for a Ray cluster out of reach or refusing
        lease = acquire(cfg.out, Backend(cfg.out))  # before the store is opened for writing
    except (MaterialError, LeaseHeld, ConnectionError) as exc:
        raise FarmError(str(exc)) from None
    except OSError as exc:  # no such bucket, access denied, out of reach after the retries
        raise FarmError(f"{cfg.out}: {type(exc).__name__}: {exc}") from None
    try:
        clear_cancel(lease.backend)  # a new submit supersedes an old cancel request
        job = prepare(cfg, specs, echo)
        if not job.todo:  # keep the finished job's state as it is
            if job.needs_screen_uv:
                echo(f"the store has no screen UV layout: farm screen-uv {cfg.out} adds it")
            n = job.layout.num_samples
            return Summary(cfg.out, n, 0, job.state.frames_skipped, {}, [], 0.0, None, 0.0, 0.0)
        return _run(job, lease, node, progress, echo, t_start, actor_cls)
    finally:
        lease.release()


def _run(
    job: Job, lease: Lease, node: str | None, progress: bool, echo, t_start: float, actor_cls
) -> Summary:
    """The job on Ray, joined as ``node`` (``farm.cluster.check_cluster``), holding the
    store's lease, to the end."""
    import ray

    cfg = job.cfg
    address, _ = address_in_force(cfg.address)
    echo(f"joining the Ray cluster at {address}" if address else "starting Ray on this machine")
    job.state.dashboard = connect(cfg.address, cfg.ray_dashboard, node)
    stop_on_sigterm()
    echo(f"ray dashboard: {job.state.dashboard or 'off'}")
    room = sizing.room(ray.available_resources(), cfg.cpus_per_worker, cfg.gpus_per_worker)
    workers = sizing.initial(
        cfg.workers, room, sum(len(job.layout.shard_materials(s)) for s in job.todo)
    )
    if workers > room:
        echo(f"{workers} workers, room for {room} now: the others wait for room "
             "(an autoscaling cluster adds nodes for them)")  # fmt: skip
    loop = Loop(job, lease, progress, actor_cls, max_commits=commit_slots(workers))
    try:
        loop.start(workers, t_start)
        while not loop.finished:
            loop.dispatch()
            for ref in loop.wait():
                loop.handle(ref)
            loop.check_placement()
            loop.resize(every=RESIZE_EVERY_S)
            loop.expire()
            loop.save(every=STATE_EVERY_S)
        if loop.cancelled:
            job.state.status = "cancelled"
        else:
            job.state.status = "failed" if loop.sched.final or loop.failed_commits else "done"
        render_end = time.perf_counter() - t_start
    except FarmError as exc:  # the job cannot go on (no worker could be placed): it failed
        job.state.status, job.state.stop_error = "failed", str(exc)
        raise
    except BaseException:
        job.state.status = "interrupted"
        raise
    finally:
        with sigterm_held():  # a SIGTERM now would leave the state unsaved and Ray running
            loop.close()
            ray.shutdown()
    return Summary(
        store=cfg.out,
        frames_total=job.layout.num_samples,
        frames_rendered=job.state.frames_done,
        frames_skipped=job.state.frames_skipped,
        failed_materials=dict(loop.sched.final),
        failed_shards=sorted(loop.shards.dead),
        wall_s=time.perf_counter() - t_start,
        dashboard=job.state.dashboard,
        startup_s=loop.startup_s if loop.startup_s is not None else time.perf_counter() - t_start,
        render_end_s=render_end,
        failed_commits=dict(loop.failed_commits),
        cancelled=loop.cancelled,
        failed_attempts=loop.sched.total_failures(),
    )


class Loop:
    """One job's event loop over Ray: the pool, the scheduler and the shard assembly; the
    tasks in flight (``report ref -> (worker, material, arrays ref)``), the whole shards
    waiting for a commit slot and the commits in flight (``ref -> shard``)."""

    def __init__(self, job: Job, lease: Lease, progress: bool, actor_cls, max_commits: int):
        cfg, layout = job.cfg, job.layout
        self.job, self.cfg, self.state, self.lease = job, cfg, job.state, lease
        self.pool = WorkerPool(cfg, job.state, actor_cls)
        self.sched = Scheduler(
            (m for s in job.todo for m in layout.shard_materials(s)),
            max_attempts=cfg.max_attempts,
            backoff_s=cfg.backoff_s,
            blocklist_after=cfg.blocklist_after,
            timeout_s=cfg.task_timeout_s * (cfg.suns + 1),
            pipeline=PIPELINE,
        )
        self.shards = ShardAssembly(layout)
        self.refs: dict[object, InFlight] = {}  # report ref -> the task it answers
        self.tickets = 0  # the last task's ticket (what a revocation names)
        self.recalled: set = set()  # refs of recalled tasks' runs: their outcome is dropped
        self.whole: collections.deque = collections.deque()  # (shard, arrays refs)
        self.commits: dict[object, tuple[int, list]] = {}  # ref -> (shard, its results)
        self.max_commits = max_commits
        self.failed_commits: dict[int, str] = {}
        self.cancelled = False  # a cancel request was seen: dispatch nothing more
        self.first: set[str] = set()
        self.startup_s: float | None = None  # until the first workers answer
        self.t_start = 0.0
        self.last_live = self.last_save = self.last_resize = now()
        self.uv_ref: tuple[object, str] | None = None  # (ref, worker) of the screen UV render
        self.uv_tries = 0
        remaining = sum(len(layout.shard_samples(s)) for s in job.todo)
        self.bar = progress_bar(
            total=remaining, desc="frames", unit="frame", disable=not progress, smoothing=0.1
        )

    @property
    def finished(self) -> bool:
        """Every task done or final (or, cancelled, every task in flight ended), and every
        whole shard's commit ended."""
        tasks_over = not self.refs if self.cancelled else self.sched.finished
        return tasks_over and not self.whole and not self.commits and self.uv_ref is None

    def start(self, workers: int, t_start: float) -> None:
        """Start the workers and save the job's state at once: ``farm status`` and the
        dashboard see a running job (and a driver killed before its next save is called
        lost) from its first moment, before any shard is committed."""
        self.t_start = t_start
        self.first = {self.pool.start() for _ in range(workers)}
        self.state.save(self.job.store.backend)
        self.last_save = now()

    def dispatch(self) -> None:
        if self.cancelled:
            return
        self.ask_screen_uv()  # first in its worker's queue
        usable, known = self.pool.usable(), self.known()
        for wid, m in self.sched.recall(usable, known, now()):
            ref = next(
                r for r, f in self.refs.items()
                if f.worker == wid and f.material == m and r not in self.recalled
            )  # fmt: skip
            self.recalled.add(ref)
            self.pool.revoke(wid, self.refs[ref].ticket)
            self.state.workers[wid].recalled += 1
        for wid, m in self.sched.dispatch(usable, known, now()):
            task = task_for(self.cfg, m, self.job.specs[m]).to_dict()
            self.tickets += 1
            report, arrays = self.pool.submit(wid, task, self.cfg.task_timeout_s, self.tickets)
            self.refs[report] = InFlight(wid, m, arrays, self.tickets)
            w = self.state.workers[wid]
            if w.status == "idle":
                w.status, w.current = "busy", m

    def known(self) -> list[str]:
        """The workers a retry may wait for (:func:`farm.scheduler.awaited`): a starting
        worker's ``last_seen`` is when it was started, until it answers."""
        starting = set(self.pool.starting.values())
        placed = [w for w in self.pool.actors if w not in starting]
        since = {w: self.state.workers[w].last_seen for w in starting if w in self.pool.actors}
        return awaited(placed, since, now(), self.cfg.retry_wait_s)

    def wait(self) -> list:
        import ray

        waiting = [*self.refs, *self.pool.starting, *self.commits]
        if self.uv_ref is not None:
            waiting.append(self.uv_ref[0])
        if not waiting:
            time.sleep(0.05)
            return []
        # every event that is ready, in one pass when several are; nothing is fetched here
        # (the small reports are read by ``handle``, the arrays never come to this process)
        ready = ray.wait(waiting, num_returns=1, timeout=0.25, fetch_local=False)[0]
        if ready and len(waiting) > 1:
            ready = ray.wait(waiting, num_returns=len(waiting), timeout=0, fetch_local=False)[0]
        return ready

    def handle(self, ref) -> None:
        """A worker answered its start, a task ended (result or error), or a commit did."""
        import ray
        from ray.exceptions import RayActorError, RayTaskError

        if ref in self.commits:
            self.committed(ref)
            return
        if self.uv_ref is not None and ref == self.uv_ref[0]:
            self.screen_uv_done(ref)
            return
        if ref in self.pool.starting:
            self.pool.ready(ref)
            if self.startup_s is None and self.first.isdisjoint(self.pool.starting.values()):
                self.startup_s = time.perf_counter() - self.t_start
            return
        if ref not in self.refs:  # dropped by an earlier event of the same batch (removal)
            return
        wid, m, arrays, _ = self.refs.pop(ref)
        w = self.state.workers[wid]
        w.last_seen, w.current = now(), None
        if ref in self.recalled:  # skipped (revoked) or run all the same: dropped
            self.recalled.discard(ref)
            read_errors((ref, arrays))
            self.sched.dropped(wid, m, now())
            self.settle(wid)
            return
        try:
            res = ray.get(ref)
        except RayActorError as exc:
            started = self.sched.started_at(wid, m) or now()
            if m in self.sched.timed_out:
                error = f"timed out after {now() - started:.0f} s (worker killed)"
            else:
                error = f"worker died: {type(exc).__name__}"
            self.remove(wid, "dead", keep=m)
            self.failed(wid, m, error)
            return
        except RayTaskError as exc:
            read_errors((arrays,))
            cause = exc.cause if getattr(exc, "cause", None) else exc
            self.failed(wid, m, f"{type(cause).__name__}: {str(cause).splitlines()[0]}")
            self.settle(wid)
            return
        self.sched.completed(wid, m, now())
        self.settle(wid)
        self.completed(wid, m, res, arrays)

    def ask_screen_uv(self) -> None:
        """Have a worker render the store's screen UV layout, when the store lacks one."""
        if not self.job.needs_screen_uv or self.uv_ref is not None:
            return
        usable = self.pool.usable()
        if usable and self.uv_tries < SCREEN_UV_TRIES:
            s = default_supersample(self.cfg.resolution)
            self.uv_ref = (self.pool.screen_uv(usable[0], s), usable[0])

    def screen_uv_done(self, ref) -> None:
        """The layout came back: keep it with the store; a failure is tried again on another
        worker (up to ``SCREEN_UV_TRIES``), and never fails the job."""
        import ray

        wid = self.uv_ref[1]
        self.uv_ref = None
        self.uv_tries += 1
        try:
            put_screen_uv(self.job.store, ray.get(ref))
        except Exception as exc:  # noqa: BLE001 - the renders go on; farm screen-uv can redo it
            error = f"{type(exc).__name__}: {str(exc).splitlines()[0] if str(exc) else ''}"
            log.warning("screen UV layout (worker %s): %s", wid, error)
            self.state.screen_uv_error = error
            return
        self.job.needs_screen_uv = False
        self.state.screen_uv_error = None

    def settle(self, wid: str) -> None:
        """The worker's status after a task left it: busy with its next one, or idle."""
        w = self.state.workers[wid]
        if w.status in ("idle", "busy"):
            w.current = self.sched.running(wid)
            w.status = "idle" if w.current is None else "busy"

    def remove(self, wid: str, status: str, keep: int | None = None) -> None:
        """Take ``wid`` out (its other tasks back to the queue) and start a replacement."""
        back = set(self.sched.remove_worker(wid, keep))
        for r, f in list(self.refs.items()):
            if f.worker == wid and f.material in back:
                del self.refs[r]
        self.pool.replace(wid, status)

    def failed(self, wid: str, m: int, error: str) -> None:
        out = self.sched.failed(wid, m, error, now())
        self.state.workers[wid].failures += 1
        spec = self.job.specs[m]
        self.state.failures[str(m)] = {
            "kind": spec.kind,
            "source": spec.source_id,
            "attempts": out.attempts,
            "errors": self.sched.errors[m][-5:],
            "final": out.final,
        }
        if out.final:
            self.shards.kill(m)
            self.state.shards_failed = sorted(self.shards.dead)
        if out.blocklist and wid in self.pool.actors:
            self.remove(wid, "blocklisted")
        if not out.final and not self.cancelled:  # before its backoff ends: a fresh worker
            self.grow()  # for a retry that only workers which failed it would take
        self.postfix()

    def completed(self, wid: str, m: int, res: dict, arrays) -> None:
        w = self.state.workers[wid]
        w.frames += len(res["seconds"])
        w.materials += 1
        w.frame_seconds += float(sum(res["seconds"]))
        w.recycled += int(res["recycled"])
        w.host, w.pid = res["host"], res["pid"]
        self.bar.update(len(res["seconds"]))  # rendered; state.frames_done counts committed ones
        self.state.frames_rendered += len(res["seconds"])
        if str(m) in self.state.failures:  # an earlier failure was retried successfully
            self.state.failures[str(m)]["recovered"] = True
        whole = self.shards.add(m, arrays)
        if whole is not None:
            self.whole.append(whole)
        self.start_commits()

    def start_commits(self) -> None:
        """Start the waiting shards' commits, up to ``max_commits`` in flight."""
        layout, specs = self.job.layout, self.job.specs
        while self.whole and len(self.commits) < self.max_commits:
            shard, arrays = self.whole.popleft()
            records = [
                {"kind": specs[i].kind, "source_id": specs[i].source_id, "spec": specs[i].to_dict()}
                for i in layout.shard_materials(shard)
            ]
            self.commits[self.pool.commit(shard, records, arrays)] = (shard, arrays)

    def committed(self, ref) -> None:
        """A commit ended: count the shard, or send its materials back, or record why not."""
        import ray
        from ray.exceptions import ObjectLostError, RayError

        shard, arrays = self.commits.pop(ref)
        layout = self.job.layout
        try:
            report = ray.get(ref)
        except ObjectLostError as exc:  # a node holding results went away: render those again
            self.results_lost(shard, arrays, type(exc).__name__)
        except RayError as exc:
            cause = getattr(exc, "cause", None) or exc
            error = f"{type(cause).__name__}: {str(cause).splitlines()[0] if str(cause) else ''}"
            self.failed_commits[shard] = error
            self.shards.dead.add(shard)
            self.state.shards_failed = sorted(self.shards.dead)
            self.state.commit_failures[str(shard)] = error
        else:
            for line in report["retries"]:
                log.warning("shard %d, written on %s: %s", shard, report["host"], line)
            self.state.shards_committed += 1
            self.state.frames_done += len(layout.shard_samples(shard))
        self.start_commits()
        self.postfix()

    def results_lost(self, shard: int, arrays: list, why: str) -> None:
        """``shard``'s commit found results lost: the materials whose results Ray holds as
        lost go back to the queue and the others wait again for them; when none can be told
        lost, the whole shard goes back."""
        members = list(self.job.layout.shard_materials(shard))
        lost = self.pool.lost(arrays) or list(range(len(members)))
        pairs = enumerate(zip(members, arrays, strict=True))
        self.shards.keep(shard, {m: a for i, (m, a) in pairs if i not in lost})
        materials = [members[i] for i in lost]
        log.warning("shard %d: the results of %d of its %d materials were lost (%s); rendering "
                    "them again", shard, len(materials), len(members), why)  # fmt: skip
        self.sched.requeue(materials)
        self.bar.total += len(materials) * self.job.layout.suns_per_material
        if not self.cancelled:  # now, not at the next resize: by then the idle take them
            self.grow()

    def postfix(self) -> None:
        self.bar.set_postfix(
            shards=f"{self.state.shards_committed}/{self.job.layout.num_shards}",
            failures=self.sched.total_failures(),
            refresh=False,
        )

    def check_placement(self) -> None:
        """Stop when no worker has been alive for ``placement_timeout_s``."""
        cfg = self.cfg
        if self.pool.usable() or self.refs or self.commits:
            self.last_live = now()
        elif now() - self.last_live > cfg.placement_timeout_s:
            why = "; ".join(self.pool.start_failures[-3:]) or (
                f"Ray could not place a worker needing {cfg.cpus_per_worker} CPU(s) and "
                f"{cfg.gpus_per_worker} GPU(s)"
            )
            raise FarmError(f"no live worker for {cfg.placement_timeout_s:.0f} s: {why}")

    def resize(self, every: float) -> None:
        """``every`` seconds at most: give up the workers waiting for room that the queue
        would not keep busy, release the idle ones at the job's tail, and start workers on
        what the cluster gained since the last look (with ``--workers N``: up to N again)
        (:mod:`farm.sizing`)."""
        if self.cancelled or now() - self.last_resize < every:
            return
        self.last_resize = now()
        self.trim()
        self.release()
        self.grow()

    def idle(self) -> list[str]:
        """Placed workers that hold nothing (not even a recalled run) and are not rendering
        the screen UV layout."""
        uv_worker = self.uv_ref[1] if self.uv_ref is not None else None
        return [w for w in self.pool.usable() if not self.sched.assigned.get(w) and w != uv_worker]

    def release(self) -> None:
        """Let the idle workers go at the job's tail (:func:`farm.sizing.release`): their
        Blenders end, and on an autoscaling cluster their nodes can go. A node that holds
        results waiting for their shard's commit is not idle to Ray's autoscaler
        (docs/farm.md); were it taken all the same, :meth:`committed` renders them again."""
        idle, queued = self.idle(), len(self.sched.queue)
        running = sum(self.sched.running(w) is not None for w in self.sched.assigned)
        n = sizing.release(len(idle), queued, running)
        for wid in idle[:n]:
            self.pool.remove(wid, "released")
        if n:
            names = ", ".join(idle[:5]) + (f" and {n - 5} more" if n > 5 else "")
            self.bar.write(f"{queued} tasks queued, {running} running: releasing {n} idle "
                           f"worker{'s' if n > 1 else ''} ({names})")  # fmt: skip

    def trim(self) -> None:
        """Give up the workers waiting for room beyond what the queued tasks, and those
        waiting behind another at a busy worker, could keep busy
        (:func:`farm.sizing.surplus`): on an autoscaling cluster each is a node asked for."""
        queued = len(self.sched.queue) + self.sched.waiting()
        surplus = sizing.surplus(len(self.pool.starting), queued)
        if surplus:
            self.pool.give_up(surplus)
            self.bar.write(f"{queued} tasks queued: giving up {surplus} of the workers "
                           "waiting for room")  # fmt: skip

    def grow(self) -> None:
        """Start workers on what the cluster gained since the last look, or with ``--workers
        N`` up to N again, for the queued tasks that the idle workers will not take."""
        import ray

        cfg, starting = self.cfg, len(self.pool.starting)
        placed, queued = len(self.pool.actors) - starting, len(self.sched.queue)
        if cfg.workers:
            fit = cfg.workers
        else:  # this job's workers hold their resources: not in the free ones
            free = sizing.room(ray.available_resources(), cfg.cpus_per_worker, cfg.gpus_per_worker)
            fit = placed + free
        more = sizing.to_start(fit, placed, starting, queued, self.sched.takers(self.idle()))
        if not more:
            return
        if cfg.workers:
            self.bar.write(f"{queued} tasks queued: starting {more} worker{'s' if more > 1 else ''}"
                           f" again (--workers {cfg.workers})")  # fmt: skip
        else:
            self.bar.write(f"the cluster holds {fit} workers: starting {more} more")
        for _ in range(more):
            self.pool.start()
        self.max_commits = max(self.max_commits, commit_slots(placed + more))

    def expire(self) -> None:
        """Kill the workers whose running task is past the guard; the task then fails (a
        recalled task's run fails nothing)."""
        for wid, m in self.sched.expired(now()):
            if wid in self.pool.actors:
                self.remove(wid, "dead", keep=m)  # its ref now fails with RayActorError

    def save(self, every: float) -> None:
        if now() - self.last_save > every:
            if not self.cancelled and cancel_requested(self.lease.backend):
                self.cancelled = True
                self.bar.write("cancel requested: finishing the tasks in flight")
            self.lease.renew()
            self.state.save(self.job.store.backend)
            self.last_save = now()

    def close(self) -> None:
        """Stop the workers and save the job state. Saved first too: an interrupted driver
        may be killed before its workers are stopped (``ray job stop`` waits 3 s)."""
        self.bar.close()
        interrupted = self.state.status == "interrupted"
        if interrupted:
            self.state.save(self.job.store.backend)
        for wid in self.sched.only_marks():  # busy with runs that are dropped: not waited for
            if wid in self.pool.actors:
                self.pool.remove(wid, "stopped")
        self.pool.stop_all(wait_s=2 if interrupted else 15)
        deadline = time.monotonic() + 2  # the runs left (dropped, or killed just now): read
        for ref, f in self.refs.items():
            read_errors((ref, f.arrays), wait_s=max(0.0, deadline - time.monotonic()))
        self.state.save(self.job.store.backend)
