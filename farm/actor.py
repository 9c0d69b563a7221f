"""The farm's Ray worker: one kept-loaded Blender scene, material after material.

``RenderWorker`` is a plain class that the driver wraps with ``ray.remote``. It never imports
``bpy`` itself: it drives a ``render_jobs.process.RenderProcess`` child, so it can recycle
Blender (after ``recycle_after`` renders or above ``rss_limit_mb`` resident, BlenderProc's
memory growth) and kill a hung render (per-sun ``timeout``) without losing the actor. With
GPUs, Ray sets ``CUDA_VISIBLE_DEVICES`` to the actor's one GPU, so each Blender sees only its
own (``device`` OPTIX or CUDA).

A task waiting in a worker's queue may be given to another worker (the scheduler's recall):
the driver then *revokes* its ticket, and the worker skips that task when it comes to it
(:class:`Revocable`). ``revoke`` runs in the actor's own ``control`` concurrency group (see
:data:`CONCURRENCY_GROUPS`), so it is answered while a render runs, where a plain call would
wait behind the queue it is meant to shorten.

Tests plant failures through :mod:`farm.faults` (``SHADERBALL_FARM_FAULTS``); unset, the
actor runs as in production.
"""

from __future__ import annotations

import os
import socket
import time

from farm import faults
from render_jobs.materials import load_map_bytes
from render_jobs.process import RenderProcess
from render_jobs.specs import RenderJob, RenderSettings
from storage.convert import pack_material

#: the actor's concurrency groups besides Ray's default one (one thread, where the renders
#: run in order): ``control`` runs :meth:`Revocable.revoke` beside a render
CONCURRENCY_GROUPS = {"control": 1}


class Revocable:
    """Tickets of queued tasks that are to be skipped: a task submitted with ticket ``t``
    (unique within a job) returns :meth:`skipped`'s report at once after ``revoke(t)``. A
    revocation that comes after its task started changes nothing (the driver drops that
    run's outcome either way)."""

    def __init__(self) -> None:
        self._revoked: set[int] = set()

    def revoke(self, ticket: int) -> None:
        self._revoked.add(ticket)

    def skipped(self, ticket: int | None, job: dict) -> tuple[dict, dict] | None:
        """``(report, {})`` when ``ticket`` was revoked (and the ticket forgotten), else
        ``None``."""
        if ticket is None or ticket not in self._revoked:
            return None
        self._revoked.discard(ticket)
        return {"material_index": job["material_index"], "skipped": True}, {}


class RenderWorker(Revocable):
    """Renders :class:`RenderJob`\\ s; each result is a small report for the driver and the
    packed, store-ready arrays, which go to the shard's commit (:mod:`farm.commit`)."""

    def __init__(self, worker_id: str, settings: dict, recycle_after: int, rss_limit_mb: int):
        super().__init__()
        self.worker_id = worker_id
        self.settings = RenderSettings.from_dict(settings)
        self.recycle_after = recycle_after
        self.rss_limit = rss_limit_mb << 20
        self.process = RenderProcess(self.settings).start()  # Blender loads with the actor
        self.renders_since_start = 0
        self.recycled = 0
        self.faults = faults.from_env()

    def info(self) -> dict:
        return {
            "worker": self.worker_id,
            "pid": os.getpid(),
            "host": socket.gethostname(),
            "blender_pid": self.process.pid,
            "nice": os.getpriority(os.PRIO_PROCESS, 0),
        }

    def render(self, job: dict, timeout_s: float, ticket: int | None = None) -> tuple[dict, dict]:
        """Render one material under all its suns (``job``: ``RenderJob.to_dict()``); returns
        ``(report, arrays)``, two Ray objects when called with ``num_returns=2``; nothing is
        rendered when ``ticket`` was revoked (:class:`Revocable`)."""
        skipped = self.skipped(ticket, job)
        if skipped is not None:
            return skipped
        task = RenderJob.from_dict(job)
        if self.faults is not None:
            self.faults.before_render(self.worker_id, task.material_index)
        # the 8-bit maps Blender's textures hold, a file read straight to them: a quarter of
        # the memory held while reading and while Blender renders (160 MB, not 640 MB, at 4K)
        maps = load_map_bytes(task.material)
        t0 = time.perf_counter()
        result = self.process.render_material(
            maps, list(task.suns), list(task.seeds), timeout=timeout_s
        )
        wall = time.perf_counter() - t0
        self.renders_since_start += len(task.suns)
        recycled = False
        if self.renders_since_start >= self.recycle_after or result.rss_bytes > self.rss_limit:
            self.process.close()  # the next task starts a fresh Blender
            self.renders_since_start = 0
            self.recycled += 1
            recycled = True
        arrays = pack_material(result)
        report = {
            "material_index": task.material_index,
            "seconds": arrays["seconds"].tolist(),
            "wall_s": wall,
            "rss_mb": result.rss_bytes / 2**20,
            "recycled": recycled,
            "geometry_hash": result.geometry_hash,
            **self.info(),
        }
        return report, arrays

    def screen_uv(self, supersample: int):
        """The scene's :class:`render_jobs.screen_uv.ScreenUV` at this worker's settings."""
        return self.process.screen_uv(supersample)

    def close(self) -> None:
        if self.faults is not None:
            self.faults.on_close()
        self.process.close()
