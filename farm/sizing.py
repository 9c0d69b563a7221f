"""How many render workers a job runs, as plain decisions: no Ray, no clock.

With ``--workers N`` a job runs N workers, no more than its materials. Those Ray cannot place
yet wait for room, and on an autoscaling cluster they are the demand the autoscaler adds nodes
for: ``--workers`` is how large a job asks such a cluster to grow.

Without it the job sizes itself to the room the cluster has and follows it as nodes join: a
worker group scaled up by hand, an autoscaler's node, a machine started with ``ray start
--address``. The driver reads the cluster's free resources every few seconds and starts what
:func:`to_start` says. Room is what is free (Ray's ``available_resources()``), not the
cluster's size: CPUs that another Ray job holds on a shared cluster are not this job's. Such a
job asks an autoscaler for one node at most (its one worker that waits when nothing is free).

It never stops a worker that has work to shrink: a node that leaves takes its workers with
it, and the driver replaces each dead one, which waits for room. Workers still waiting for room
beyond what the queue can keep busy are given up (:func:`surplus`), and at a job's tail the
placed workers left with nothing to do are released (:func:`release`), so that an autoscaler
can take their nodes back while the last tasks run. A job that lost workers so (a retry, or
results lost with a node, filling the queue again) starts them again, up to ``--workers N``
or the room there is (:func:`to_start`); a retry starts one even where the worker that failed
it idles, so that it runs elsewhere.
"""

from __future__ import annotations

from collections.abc import Mapping


def room(resources: Mapping[str, float], cpus_per_worker: int, gpus_per_worker: float) -> int:
    """The workers that ``resources`` hold (0 when none fits): CPUs over ``cpus_per_worker``,
    and GPUs over ``gpus_per_worker`` when a worker needs any."""
    n = int(resources.get("CPU", 0) // max(cpus_per_worker, 1))
    if gpus_per_worker:
        n = min(n, int(resources.get("GPU", 0) // gpus_per_worker))
    return max(0, n)


def initial(fixed: int | None, room: int, tasks: int) -> int:
    """The workers a job starts with: ``fixed`` (``--workers``) when given, else those the
    cluster has ``room`` for (at least 1, which waits when there is none), but no more than
    its ``tasks`` (materials to render) can keep busy: on an autoscaling cluster a worker that
    waits for room is a node the autoscaler adds."""
    return max(1, min(fixed or room, tasks))


def to_start(fit: int, placed: int, starting: int, queued: int, taken: int = 0) -> int:
    """Workers to start now toward ``fit`` (what the cluster holds, or ``--workers``) for a job
    that has ``placed`` workers, ``starting`` ones not placed yet and ``queued`` tasks that no
    worker holds, ``taken`` of which its idle workers will take.

    None while a worker is still starting: Ray has not found it room yet (a node still
    joining, resources taken by another job), and more would only wait beside it. None beyond
    what the queue can keep busy, less what the idle workers take (a retry waiting out its
    backoff): a job's last tasks do not start Blenders. A retry that every idle worker failed
    is not theirs (:meth:`farm.scheduler.Scheduler.takers`): it starts a fresh worker where
    there is room, so that it runs elsewhere even at a job's tail, after the other workers were
    released."""
    if starting:
        return 0
    return max(0, min(fit - placed, queued - taken))


def surplus(starting: int, queued: int) -> int:
    """Workers still waiting for room (``starting``) to give up: those beyond what the
    ``queued`` tasks could keep busy (those no worker holds, and those waiting behind another
    at a busy worker, which a worker that comes up takes). On an autoscaling cluster each
    waiting worker is a node asked for, and at a job's tail none of those is needed."""
    return max(0, starting - queued)


def release(idle: int, queued: int, running: int) -> int:
    """Placed workers holding nothing (``idle``) to let go: every one while no task is
    ``queued`` and other workers still have tasks ``running`` (a job's tail: on an
    autoscaling cluster each is a node that can go while the last renders finish, which can
    take minutes); none otherwise. A queued task, a retry waiting out its backoff included, is
    theirs to take, and when no task runs the job is ending and every worker stops anyway."""
    return idle if not queued and running else 0
