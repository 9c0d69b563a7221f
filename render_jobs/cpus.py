"""How many CPUs this process may use, for sizing pools of processes and threads."""

from __future__ import annotations

import os
from pathlib import Path

CGROUP_CPU_MAX = Path("/sys/fs/cgroup/cpu.max")


def usable_cpus(cpu_max: Path = CGROUP_CPU_MAX) -> int:
    """CPUs this process may use: its affinity (every CPU where the OS does not say: macOS),
    bounded by a cgroup v2 CPU quota if any (a container's CPU limit)."""
    cpus = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count()
    try:
        quota, period = cpu_max.read_text().split()[:2]
        if quota != "max":
            cpus = min(cpus or 1, max(1, int(quota) // int(period)))
    except (OSError, ValueError):
        pass
    return max(1, cpus or 1)


def omp_threads() -> int | None:
    """``OMP_NUM_THREADS`` when it is a positive integer (Ray sets it to a task's or an
    actor's CPUs), else ``None``: another value is ignored, as OpenMP ignores it."""
    omp = os.environ.get("OMP_NUM_THREADS", "").strip()
    return int(omp) if omp.isdigit() and int(omp) > 0 else None
