"""A Blender worker process: a :class:`ShaderballRenderer` in a spawned child process.

The parent never imports ``bpy``. The child builds the scene once, then serves requests (a
material under its suns, or the scene's screen UV layout) until closed, and leaves with
``os._exit`` (bpy deadlocks at normal interpreter exit). Blender's stdout chatter goes to
``log_path`` (or /dev/null). The parent owns the child's scratch folder (in /dev/shm when
it has room: EXRs, texture PNGs and Blender's own session folder) and removes it when the
child ends, even when it was killed. A request that raises in the child comes back as
:class:`RenderError` or :class:`MaterialError` with the child's message; a child that dies
(segfault, OOM kill) raises :class:`RenderError` naming its exit code, and the next request
starts a fresh child. On Linux the child dies with its parent (a Ray actor killed mid-render
leaves no Blender rendering on).
"""

from __future__ import annotations

import contextlib
import multiprocessing as mp
import os
import shutil
import signal
import sys
import tempfile
import traceback
from collections.abc import Callable
from pathlib import Path

from render_jobs.errors import MaterialError, RenderError, WorkerDied
from render_jobs.materials.maps import MapBytes, MaterialMaps
from render_jobs.results import MaterialRender
from render_jobs.screen_uv import DEFAULT_SUPERSAMPLE, ScreenUV
from render_jobs.specs import RenderSettings, Sun

READY_TIMEOUT_S = 300.0
SCRATCH_PREFIX = "shaderball-worker-"
#: free space /dev/shm needs to take a child's scratch folder: its material's four 8-bit
#: texture PNGs and a sun's EXR (1.9 MB after a procedural material at 1,024² maps, 400²;
#: scanned 2K textures take several MB each), with room for other workers and Ray
SCRATCH_ROOM = 256 * 2**20


def sweep_stale_scratch(folder: str) -> None:
    """Remove scratch folders whose owning process is gone (killed before it could clean)."""
    for entry in os.scandir(folder):
        if not entry.name.startswith(SCRATCH_PREFIX):
            continue
        pid = entry.name[len(SCRATCH_PREFIX) :].split("-", 1)[0]
        if pid.isdigit() and not os.path.exists(f"/proc/{pid}"):
            shutil.rmtree(entry.path, ignore_errors=True)


def scratch_parent(shm: str = "/dev/shm") -> str | None:
    """Where a child's scratch folder goes: ``shm`` (memory) when it has
    :data:`SCRATCH_ROOM` free, else the temp folder (None). A container's own ``/dev/shm``
    is 64 MB (Docker's default), which a few workers' texture files and EXRs can fill."""
    if not os.path.isdir(shm):
        return None
    return shm if shutil.disk_usage(shm).free >= SCRATCH_ROOM else None


@contextlib.contextmanager
def thread_pool_of(threads: int):
    """Inside, load Blender so that its thread pool holds ``threads`` threads (0: all cores).

    Blender sizes its TBB pool from the process's CPU mask once, when ``bpy`` loads, whatever
    ``render.threads`` says. With ``render.threads`` below the core count, the pool's spare
    workers spin in ``sched_yield`` through every render: a 1-thread worker uses every core
    of CPU for the same frame time, so two such workers slow each other. So the
    process may use only ``threads`` CPUs while Blender loads; on leaving, every thread gets
    the full mask back, and the OS still places the worker anywhere. Linux only (elsewhere
    a no-op)."""
    full = os.sched_getaffinity(0) if hasattr(os, "sched_setaffinity") else set()
    if not threads or threads >= len(full):
        yield
        return
    os.sched_setaffinity(0, sorted(full)[:threads])
    try:
        yield
    finally:
        for tid in os.listdir("/proc/self/task"):
            with contextlib.suppress(OSError):  # a thread that ended meanwhile
                os.sched_setaffinity(int(tid), full)


def _die_with_parent(parent: int) -> None:  # in the child
    """Have the kernel kill this process when its parent goes (Linux ``PR_SET_PDEATHSIG``;
    elsewhere a no-op). The signal comes when the *thread* that started the child ends: every
    caller starts it from a thread that lasts as long as its process (its main thread; in a
    farm actor, also the one thread Ray runs the actor's default concurrency group on, where
    a recycled Blender starts)."""
    if not sys.platform.startswith("linux"):
        return
    import ctypes

    pr_set_pdeathsig = 1
    ctypes.CDLL(None, use_errno=True).prctl(pr_set_pdeathsig, signal.SIGKILL)
    if os.getppid() != parent:  # it died before the call above
        os._exit(1)


def _serve(conn, settings: dict, log_path: str | None, scratch: str, parent: int) -> None:
    """The child's life: load Blender, then answer requests until told to stop."""
    _die_with_parent(parent)
    os.environ["SHADERBALL_BLENDER_WORKER"] = "1"
    # Blender makes its session folder (``blender_XXXXXX``) under $TMPDIR when bpy loads and
    # removes it only at a normal exit, which ``os._exit`` skips: in the scratch folder, the
    # parent removes it with the rest.
    os.environ["TMPDIR"] = scratch
    log = os.open(log_path or os.devnull, os.O_WRONLY | os.O_CREAT | os.O_APPEND, 0o644)
    os.dup2(log, 1)
    code = 0
    try:
        with thread_pool_of(settings["threads"]):
            from render_jobs.blender.renderer import ShaderballRenderer

            renderer = ShaderballRenderer(RenderSettings.from_dict(settings), scratch)
        conn.send(("ready", {"geometry_hash": renderer.geometry_hash, "pid": os.getpid()}))
        while True:
            request = conn.recv()
            if request is None:
                break
            what, args = request
            try:
                if what == "screen_uv":
                    conn.send(("ok", renderer.screen_uv(*args)))
                    continue
                maps, suns, seeds = args

                def progress(done: int) -> None:
                    conn.send(("progress", done))

                conn.send(("ok", renderer.render_material(maps, suns, seeds, progress)))
            except MaterialError as exc:
                conn.send(("material", str(exc)))
            except Exception as exc:  # noqa: BLE001 - reported to the parent, which raises
                traceback.print_exc(file=sys.stderr)
                conn.send(("error", f"{type(exc).__name__}: {exc}"))
    except (EOFError, BrokenPipeError, KeyboardInterrupt):
        code = 1
    except Exception as exc:  # noqa: BLE001 - start-up failure, reported to the parent
        traceback.print_exc(file=sys.stderr)
        with contextlib.suppress(BrokenPipeError, OSError):
            conn.send(("error", f"{type(exc).__name__}: {exc}"))
        code = 1
    finally:
        sys.stdout.flush()
        sys.stderr.flush()
        os._exit(code)


@contextlib.contextmanager
def _parent_main_hidden():
    """Start a spawned child without running the parent's ``__main__`` in it again.

    ``multiprocessing``'s spawn runs the parent's main script (its ``__file__``, or the module
    its ``__spec__`` names) in the child, so that a target defined there can be found. The
    child's target is :func:`_serve`, of this module, so that run only costs: in a Ray worker
    the script is Ray's ``default_worker.py``, which imports Ray into every Blender, at each
    farm worker's start and recycle (its time and memory: ``benchmarks.worker_start``), and a
    script without an ``if __name__ == "__main__":`` guard would start its work again in the
    child. The parent's ``__main__`` goes without the two for the length of
    ``Process.start()``, which reads them.
    """
    main = sys.modules.get("__main__")
    if main is None:
        yield
        return
    saved = {k: main.__dict__[k] for k in ("__file__", "__spec__") if k in main.__dict__}
    main.__dict__.pop("__file__", None)
    main.__spec__ = None
    try:
        yield
    finally:
        main.__dict__.update(saved)
        if "__spec__" not in saved:
            del main.__spec__


class RenderProcess:
    """Renders in a child Blender process; use as a context manager.

    >>> with RenderProcess(RenderSettings(resolution=64, samples=8)) as worker:  # doctest: +SKIP
    ...     result = worker.render_material(maps, suns, seeds)
    """

    def __init__(self, settings: RenderSettings, log_path: str | Path | None = None):
        self.settings = settings
        self.log_path = str(log_path) if log_path else None
        self._proc = None
        self._conn = None
        self._scratch: str | None = None
        self.info: dict = {}

    def start(self) -> RenderProcess:
        ctx = mp.get_context("spawn")
        parent, child = ctx.Pipe()
        shm = scratch_parent()
        sweep_stale_scratch(shm or tempfile.gettempdir())
        self._scratch = tempfile.mkdtemp(prefix=f"{SCRATCH_PREFIX}{os.getpid()}-", dir=shm)
        self._proc = ctx.Process(
            target=_serve,
            args=(child, self.settings.to_dict(), self.log_path, self._scratch, os.getpid()),
            daemon=True,
        )
        with _parent_main_hidden():
            self._proc.start()
        child.close()
        self._conn = parent
        try:
            kind, payload = self._receive(READY_TIMEOUT_S)
        except WorkerDied as exc:
            raise WorkerDied(f"{exc} before it was ready; its error is above") from None
        except BaseException:  # Ctrl-C or SIGTERM while Blender loads: no child left behind
            self.close(wait_s=0)
            raise
        if kind != "ready":
            self.close()
            raise RenderError(f"Blender worker failed to start: {payload}")
        self.info = payload
        return self

    def _receive(self, timeout: float | None):
        assert self._conn is not None and self._proc is not None
        if not self._conn.poll(timeout):
            self.close()
            raise RenderError(f"Blender worker sent nothing for {timeout:.0f} s")
        try:
            return self._conn.recv()
        except (EOFError, ConnectionResetError):
            self._proc.join(timeout=5)
            code = self._proc.exitcode
            self._proc = self._conn = None
            self._remove_scratch()
            raise WorkerDied(f"Blender worker died (exit code {code})") from None

    @property
    def alive(self) -> bool:
        return self._proc is not None and self._proc.is_alive()

    @property
    def scratch(self) -> str | None:
        """The child's scratch folder (removed when the child ends)."""
        return self._scratch

    @property
    def pid(self) -> int | None:
        return self._proc.pid if self._proc is not None else None

    def render_material(
        self,
        maps: MaterialMaps | MapBytes,
        suns: list[Sun],
        seeds: list[int],
        timeout: float | None = None,
        on_progress: Callable[[int], None] | None = None,
    ) -> MaterialRender:
        """Render one material under ``suns`` (blocking).

        ``timeout``: seconds allowed per sun (None = no limit); past it the child is killed
        and :class:`RenderError` raised. ``on_progress(k)`` is called after each sun.
        """
        if not self.alive:
            self.start()
        assert self._conn is not None
        if isinstance(maps, MaterialMaps):  # as bytes: what Blender's textures hold
            maps = MapBytes.of(maps)
        self._conn.send(("render", (maps, list(suns), list(seeds))))
        kind, payload = self._receive(timeout)
        while kind == "progress":
            if on_progress is not None:
                on_progress(payload)
            kind, payload = self._receive(timeout)
        if kind == "ok":
            return payload
        if kind == "material":
            raise MaterialError(payload)
        raise RenderError(payload)

    def screen_uv(self, supersample: int = DEFAULT_SUPERSAMPLE, timeout: float = 600) -> ScreenUV:
        """The scene's UV layout as the camera sees it at ``supersample``² sub-samples a pixel
        (:mod:`render_jobs.screen_uv`), rendered in the child (blocking)."""
        if not self.alive:
            self.start()
        assert self._conn is not None
        self._conn.send(("screen_uv", (supersample,)))
        kind, payload = self._receive(timeout)
        if kind != "ok":
            raise RenderError(payload)
        return payload

    def close(self, wait_s: float = 10) -> None:
        """Ask the child to exit; kill it if it does not within ``wait_s``."""
        if self._conn is not None:
            with contextlib.suppress(BrokenPipeError, OSError):
                self._conn.send(None)
            self._conn.close()
        if self._proc is not None:
            self._proc.join(timeout=wait_s)
            if self._proc.is_alive():
                self._proc.kill()
                self._proc.join()
        self._proc = self._conn = None
        self._remove_scratch()

    def _remove_scratch(self) -> None:
        if self._scratch is not None:
            shutil.rmtree(self._scratch, ignore_errors=True)
            self._scratch = None

    def __enter__(self) -> RenderProcess:
        return self.start()

    def __exit__(self, exc_type, *exc) -> None:
        # unwinding (an error, Ctrl-C, SIGTERM): the child may be mid-frame, deaf to the ask
        self.close(wait_s=0 if exc_type else 10)
