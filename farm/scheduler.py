"""The farm's scheduling policy, as plain data and decisions: no Ray, no clock of its own.

A task is one material (all its suns), named by its material index. The scheduler holds the
queue (in shard order, so shards complete one after another and driver memory stays bounded),
each worker's assigned tasks, every attempt's error, backoff deadlines and per-worker failure
counts. The driver asks it what to hand to which worker and tells it what happened; every
method takes the current time ``now`` (seconds), so tests drive it with a fake clock.

Rules:

* **Pipelining.** A worker holds up to ``pipeline`` tasks: the first runs, the others wait in
  its actor's queue, so it never idles while the driver handles a result. Extra tasks are only
  given while the queue outnumbers the workers, starting ones included (at a job's end, and in
  a job of few materials while some workers are still starting: one each), and every worker
  gets its first task before any gets a second.
* **Recall.** A usable worker that holds nothing, with nothing in the queue it may take now,
  gets a task waiting behind another at a busy worker: :meth:`Scheduler.recall` puts that
  task at the queue's front, uncounted, and keeps a *recalled* mark of it at the busy worker
  until that run ends (:meth:`Scheduler.dropped`). The driver revokes it there, and that
  worker skips it when it comes to it; had it started already, it runs to its end all the
  same. Either way its outcome is dropped and the job does not wait for it (marks do not
  count in :attr:`Scheduler.finished`; the driver stops such a worker at the end at once),
  but a mark holds its place in its worker's queue (it counts against the pipeline, and its
  worker takes no recall: the run may be going). A job's last tasks and a worker that
  starts late thus never wait behind another worker's task.
* **Retry.** A failed task goes back to the queue's end after a backoff of
  ``backoff_s * 2**(attempt - 1)``, and is given to a worker that has not failed it, unless
  every known worker has. After ``max_attempts`` failures it is final. An idle worker that
  failed a retry does not count as its taker (:meth:`Scheduler.takers`): where the job has
  room, a fresh worker is started for it. A worker still starting is known, so waited for,
  for a while only (:func:`awaited`, ``farm submit --retry-wait``): a retry does not idle
  longer than that behind one that Ray cannot place.
* **Blocklist.** A worker with ``blocklist_after`` failures is to be removed (the driver
  replaces it).
* **Lost results.** Completed tasks whose results were lost before their shard was written
  go back to the queue's front, uncounted (:meth:`Scheduler.requeue`).
* **Removal.** A removed worker gives the tasks it holds back to the queue's front, uncounted
  (they never ran there), but for the one whose failure removed it, which fails on its own.
* **Timeout.** A running task past ``timeout_s`` is reported by :meth:`Scheduler.expired`; the
  driver kills its worker, and the failure that follows is reported as a timeout (a recalled
  task's run fails nothing: its worker's other tasks go back uncounted).
"""

from __future__ import annotations

import collections
from collections.abc import Iterable, Mapping
from dataclasses import dataclass, field


def awaited(
    placed: Iterable[str], starting: Mapping[str, float], now: float, wait_s: float
) -> list[str]:
    """The workers known to :meth:`Scheduler.dispatch` and :meth:`Scheduler.recall`: every
    ``placed`` one, and those ``starting`` (worker to when it was started) for under
    ``wait_s``. A retry waits for a known worker that has not failed it: for one that Ray
    cannot place (no room, another job holding it, an autoscaler's node still starting), no
    longer than ``wait_s``; then a worker that failed it may take it."""
    return [*placed, *(w for w, since in starting.items() if now - since < wait_s)]


@dataclass
class Assigned:
    """A task handed to a worker; ``started`` is when it began running (or was queued there)."""

    task: int
    started: float
    recalled: bool = False  # given to another worker: its run here, if any, is dropped


@dataclass
class Outcome:
    """What a failure means: ``final`` (no attempts left), ``blocklist`` (remove the worker)."""

    final: bool
    blocklist: bool
    attempts: int


@dataclass
class Scheduler:
    tasks: Iterable[int]
    max_attempts: int = 3
    backoff_s: float = 5.0
    blocklist_after: int = 3
    timeout_s: float = float("inf")
    pipeline: int = 2
    queue: collections.deque = field(init=False)
    assigned: dict[str, list[Assigned]] = field(default_factory=dict, init=False)
    attempts: collections.Counter = field(default_factory=collections.Counter, init=False)
    errors: dict[int, list[dict]] = field(default_factory=dict, init=False)
    failed_on: dict[int, set[str]] = field(default_factory=dict, init=False)
    not_before: dict[int, float] = field(default_factory=dict, init=False)
    worker_failures: collections.Counter = field(default_factory=collections.Counter, init=False)
    final: dict[int, str] = field(default_factory=dict, init=False)  # task -> last error
    timed_out: set[int] = field(default_factory=set, init=False)
    backoff_until: float = field(default=0.0, init=False)  # the last retry deadline yet

    def __post_init__(self) -> None:
        self.queue = collections.deque(self.tasks)

    @property
    def finished(self) -> bool:
        """Nothing queued and nothing assigned but recalled marks: every task is done or
        final."""
        held = (a for tasks in self.assigned.values() for a in tasks)
        return not self.queue and all(a.recalled for a in held)

    def only_marks(self) -> list[str]:
        """Workers that hold recalled marks and nothing else (their runs are dropped)."""
        return [w for w, held in self.assigned.items() if held and not self._live(w)]

    def waiting(self) -> int:
        """Tasks waiting behind another at a busy worker: what a worker that comes up takes
        (:meth:`recall`)."""
        return sum(max(0, len(self._live(w)) - 1) for w in self.assigned)

    def running(self, worker: str) -> int | None:
        held = self._live(worker)
        return held[0].task if held else None

    def _live(self, worker: str) -> list[Assigned]:
        """What ``worker`` holds, less the recalled marks."""
        return [a for a in self.assigned.get(worker, ()) if not a.recalled]

    def takers(self, idle: Iterable[str]) -> int:
        """How many queued tasks the ``idle`` workers take, one each, backoffs aside. A
        retry is none of theirs where each of them failed it: left to a worker that has not,
        even one still to be started (:func:`farm.sizing.to_start`)."""
        free, taken = list(idle), 0
        for task in self.queue:
            if not free:
                break
            tried = self.failed_on.get(task, ())
            taker = next((w for w in free if w not in tried), None)
            if taker is not None:
                free.remove(taker)
                taken += 1
        return taken

    def dispatch(self, usable: list[str], known: Iterable[str], now: float) -> list[tuple]:
        """``(worker, task)`` pairs to hand out now to the ``usable`` workers (placed and
        alive), in order. ``known``: every worker that exists, starting ones too while they
        are awaited (:func:`awaited`: a retry may wait for one that has not failed it, and a
        worker takes a second task only while the queue outnumbers them all)."""
        known = set(known)
        # a second task only while the queue outnumbers every worker, starting ones too: a
        # worker still starting takes its own share when it comes up
        depth = self.pipeline if len(self.queue) > len(known | set(usable)) else 1
        out = []
        for k in range(depth):
            for worker in usable:  # a recalled mark holds its place: Ray runs it there first
                if len(self.assigned.get(worker, ())) > k:
                    continue
                task = self._pick(worker, known, now)
                if task is not None:
                    self.queue.remove(task)
                    self.assigned.setdefault(worker, []).append(Assigned(task, now))
                    out.append((worker, task))
        return out

    def _pick(self, worker: str, known: set[str], now: float) -> int | None:
        for task in self.queue:
            if self.not_before.get(task, 0.0) <= now and self._may_run(worker, task, known):
                return task
        return None

    def _may_run(self, worker: str, task: int, known: set[str]) -> bool:
        tried = self.failed_on.get(task, set())
        return worker not in tried or known <= tried

    def recall(self, usable: list[str], known: Iterable[str], now: float) -> list[tuple]:
        """``(worker, task)`` pairs, one for each usable worker that holds nothing (not even a
        recalled mark, whose run may be going) and has nothing in the queue to take now: a
        task waiting at ``worker`` that it may run, now at the queue's front and marked
        recalled at ``worker`` (the driver revokes it there, then calls :meth:`dropped`)."""
        # the common cases first, cheaply: a queued task for every worker (when no retry
        # waits its backoff, so that every queued task may go now), or none free
        if len(self.queue) >= len(usable) and now >= self.backoff_until:
            return []
        free = [w for w in usable if not self.assigned.get(w)]  # marks too: they may be running
        if not free:
            return []
        known = set(known) | set(usable)
        idle = [w for w in free if self._pick(w, known, now) is None]
        waiting = [(w, a) for w in self.assigned for a in self._live(w)[1:]]  # once: O(workers)
        out = []
        for taker in idle:
            for i, (worker, a) in enumerate(waiting):
                if self._may_run(taker, a.task, known):
                    a.recalled = True
                    self.queue.appendleft(a.task)
                    out.append((worker, a.task))
                    del waiting[i]
                    break
        return out

    def dropped(self, worker: str, task: int, now: float) -> None:
        """The recalled ``task``'s run at ``worker`` ended (skipped, or run and dropped)."""
        self._release(worker, task, now, recalled=True)

    def _release(self, worker: str, task: int, now: float, recalled: bool = False) -> None:
        """``task`` has left ``worker``; the next task waiting there starts running now."""
        held = self.assigned.get(worker, [])
        for i, a in enumerate(held):
            if a.task == task and a.recalled == recalled:
                del held[i]
                if i == 0 and held:
                    held[0].started = now
                return

    def completed(self, worker: str, task: int, now: float) -> None:
        self._release(worker, task, now)

    def failed(self, worker: str, task: int, error: str, now: float) -> Outcome:
        """Record a failed attempt; requeue it with backoff or make it final."""
        self._release(worker, task, now)
        self.timed_out.discard(task)
        self.attempts[task] += 1
        self.failed_on.setdefault(task, set()).add(worker)
        self.errors.setdefault(task, []).append({"worker": worker, "error": error, "at": now})
        self.worker_failures[worker] += 1
        n = self.attempts[task]
        final = n >= self.max_attempts
        if final:
            self.final[task] = error
        else:
            self.not_before[task] = now + self.backoff_s * 2 ** (n - 1)
            self.backoff_until = max(self.backoff_until, self.not_before[task])
            self.queue.append(task)
        return Outcome(final, self.worker_failures[worker] >= self.blocklist_after, n)

    def remove_worker(self, worker: str, keep: int | None = None) -> list[int]:
        """``worker`` is being removed: every task it holds but ``keep`` (one that is to fail
        on its own) goes back to the queue's front, uncounted, since it never ran there; those
        tasks are returned. Its recalled marks go (those tasks are in the queue already)."""
        held = self._live(worker)
        back = [a.task for a in held if a.task != keep]
        self.assigned[worker] = [a for a in held if a.task == keep]
        self.queue.extendleft(reversed(back))
        return back

    def requeue(self, tasks: Iterable[int]) -> None:
        """Completed ``tasks`` whose results were lost before they were stored (the node that
        held them went away): back to the queue's front, uncounted."""
        self.queue.extendleft(reversed(list(tasks)))

    def started_at(self, worker: str, task: int) -> float | None:
        for a in self.assigned.get(worker, []):
            if a.task == task:
                return a.started
        return None

    def expired(self, now: float) -> list[tuple[str, int | None]]:
        """``(worker, task)`` for each running task past ``timeout_s``, newly marked as timed
        out; the caller kills the worker (and removes it). ``task`` is ``None`` for the run of
        a recalled task, which fails nothing."""
        out = []
        for worker, held in self.assigned.items():
            if not held or held[0].task in self.timed_out:
                continue
            if now - held[0].started > self.timeout_s:
                if held[0].recalled:
                    out.append((worker, None))
                    continue
                self.timed_out.add(held[0].task)
                out.append((worker, held[0].task))
        return out

    def total_failures(self) -> int:
        return sum(self.attempts.values())
