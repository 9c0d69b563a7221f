"""How many render workers a job runs, as plain decisions: no Ray, no clock.

With ``--workers N`` a job runs N workers; those Ray cannot place yet wait for room (an
autoscaler adds nodes for them). Without it the job sizes itself to the cluster and follows it
as nodes join: a worker group scaled up by hand, an autoscaler's node, a machine started with
``ray start --address``. The driver reads the cluster's resources every few seconds and starts
what :func:`to_start` says. It never stops a worker to shrink: a node that leaves takes its
workers with it, and the driver replaces each dead one, which waits for room.

Room is what is free (Ray's ``available_resources()``), not the cluster's size: CPUs that
another Ray job holds on a shared cluster are not this job's to count on.
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


def fits(resources: Mapping[str, float], cpus_per_worker: int, gpus_per_worker: float) -> int:
    """The workers a job with none yet starts toward: the :func:`room` in ``resources`` (Ray's
    ``available_resources()``), at least 1, which waits for room when there is none."""
    return max(1, room(resources, cpus_per_worker, gpus_per_worker))


def initial(fixed: int | None, fit: int, tasks: int) -> int:
    """The workers a job starts with: ``fixed`` (``--workers``) when given, else those the
    cluster ``fit``s, but no more than its ``tasks`` (materials to render) can keep busy."""
    return fixed if fixed else max(1, min(fit, tasks))


def to_start(fit: int, placed: int, starting: int, queued: int) -> int:
    """Workers to start now toward the ``fit`` of a cluster that holds ``placed`` workers, with
    ``starting`` ones not placed yet and ``queued`` tasks that no worker holds.

    None while a worker is still starting: Ray has not found it room yet (a node still
    joining, resources taken by another job), and more would only wait beside it. None beyond
    what the queue can keep busy: a job's last tasks do not start Blenders."""
    if starting:
        return 0
    return max(0, min(fit - placed, queued))
