"""Fault injection for the farm's tests: planted failures in the render actor.

``SHADERBALL_FARM_FAULTS`` holds JSON; unset (production), :func:`from_env` returns ``None``
and the actor never calls in here. Keys:

- ``fail_materials``: material indices that raise every time;
- ``flaky_materials``: material indices that raise on their first try: each worker's first,
  or with ``flaky_marker`` (a path) the job's first, whichever worker makes it (the file
  ``<path>.<material>`` records it);
- ``hang_materials``: material indices that sleep past any timeout;
- ``bad_workers``: worker ids whose every task raises;
- ``slow_s``: seconds to sleep before each task;
- ``slow_materials``: material index (a JSON key: a string) to seconds to sleep before it;
- ``hold_while``: a path; each task waits while that file exists, after creating the file
  ``<path>.held`` to say so. Set in one Ray node's environment only, it keeps that node's
  worker busy for as long as a test needs, and tells the test when it is;
- ``hold_materials``: ``{"while": path, "materials": [...]}``, or a list of such holds; a
  task of those materials waits while that file exists (a job that cannot end before a test
  lets it; with a list, materials let go one after another);
- ``wait_for``: a path; each task waits until that file exists (another node's ``.held``
  file: this node's worker cannot finish the job before that node's worker has a task);
- ``trace``: a path; each task appends ``<worker> <material>`` to it as it starts;
- ``wait_for_worker``: worker id to worker id; each task of the first waits until the
  ``trace`` holds a task of the second (a replacement worker gets work, however long it
  takes to start);
- ``closing``: a path; a worker asked to close creates it, then sleeps ``close_s`` seconds
  (the driver is in its clean-up for that long, and the test knows when).
"""

from __future__ import annotations

import json
import os
import time

from render_jobs.errors import RenderError

FAULTS_ENV = "SHADERBALL_FARM_FAULTS"


class Faults:
    def __init__(self, plan: dict):
        self.plan = plan
        self.tried: set[int] = set()

    def before_render(self, worker: str, material: int) -> None:
        """Raise, sleep or hang as the plan says for ``material`` on ``worker``."""
        f = self.plan
        if f.get("trace"):
            with open(f["trace"], "a") as trace:
                trace.write(f"{worker} {material}\n")
        time.sleep(
            float(f.get("slow_s", 0)) + float(f.get("slow_materials", {}).get(str(material), 0))
        )
        while f.get("wait_for") and not os.path.exists(f["wait_for"]):
            time.sleep(0.1)
        if other := f.get("wait_for_worker", {}).get(worker):
            while not _traced(f["trace"], other):
                time.sleep(0.1)
        hold = f.get("hold_while")
        if hold and os.path.exists(hold):
            open(f"{hold}.held", "w").close()
            while os.path.exists(hold):
                time.sleep(0.1)
        holds = f.get("hold_materials", [])
        for held in [holds] if isinstance(holds, dict) else holds:
            while material in held["materials"] and os.path.exists(held["while"]):
                time.sleep(0.1)
        if worker in f.get("bad_workers", []):
            raise RenderError(f"injected fault: worker {worker} is bad")
        if material in f.get("fail_materials", []):
            raise RenderError(f"injected fault: material {material} always fails")
        if material in f.get("flaky_materials", []) and self._first_try(material):
            raise RenderError(f"injected fault: material {material} fails once")
        if material in f.get("hang_materials", []):
            time.sleep(3600)

    def _first_try(self, material: int) -> bool:
        """Whether this is ``material``'s first try: on this worker, or with ``flaky_marker``
        in the job (the marker file, created exclusively, is shared by every worker)."""
        marker = self.plan.get("flaky_marker")
        if marker is None:
            first = material not in self.tried
            self.tried.add(material)
            return first
        try:
            open(f"{marker}.{material}", "x").close()
        except FileExistsError:
            return False
        return True

    def on_close(self) -> None:
        """Say that the worker is closing, and take ``close_s`` seconds to."""
        if self.plan.get("closing"):
            open(self.plan["closing"], "w").close()
            time.sleep(float(self.plan.get("close_s", 0)))


def _traced(trace: str, worker: str) -> bool:
    """Whether the ``trace`` file holds a task of ``worker``."""
    with open(trace) as lines:
        return any(line.split()[0] == worker for line in lines)


def from_env() -> Faults | None:
    plan = json.loads(os.environ.get(FAULTS_ENV, "") or "{}")
    return Faults(plan) if plan else None
