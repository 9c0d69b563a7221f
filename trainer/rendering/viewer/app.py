"""``trainer viewer``: the web server around :class:`trainer.rendering.viewer.engine.Engine`.

Routes: ``/`` (the page), ``/api/materials`` (the gallery, JSON), ``/api/thumb?m=ID`` (a
gallery picture), ``/api/frame?m=ID&az=&el=&t=&<edits>&fmt=jpeg|png[&download=1]`` (a frame;
``Server-Timing`` says what it took), ``/api/truth?m=ID&k=K`` (a stored material under its
k-th stored sun: Cycles, network, error, PSNR; JSON with base64 PNGs), ``POST /api/upload``
(multipart files; the server's POST secret in ``X-Shaderball-Secret``). Built on
:mod:`shaderball.web` like the farm dashboard: 127.0.0.1 by default, a token on any other address.
Frames are made one at a time on one worker thread (the network uses every core); gallery
pictures on another, so a gallery of large materials never holds a frame back, and are kept
once made. A request that fails gets its one-line reason with status 400 (413 for an upload
that is too big), and the server goes on.
"""

from __future__ import annotations

import asyncio
import base64
import contextlib
import functools
import io
import os
import re
import shutil
import sys
import tempfile
import threading
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

from aiohttp import web
from PIL import Image

from render_jobs.errors import MaterialError
from render_jobs.tonemap import to_uint8, tonemap
from shaderball.web import application
from trainer.rendering.base import NoScreenUV, material_mapper
from trainer.rendering.load import load_renderer
from trainer.rendering.viewer import page
from trainer.rendering.viewer.engine import Engine, Light
from trainer.rendering.viewer.materials import MAX_UPLOAD_BYTES, Edits, Library
from trainer.rendering.viewer.recent import Recent
from trainer.rendering.viewer.thumbs import colour_preview

THUMB = 96
#: how much nicer than the rest of the viewer its gallery-picture thread runs
THUMB_NICE = 10


class Viewer:
    """The engine, its worker thread and its temporary folder (removed on shutdown)."""

    def __init__(self, engine: Engine, upload_dir: Path, info: dict):
        self.engine, self.upload_dir, self.info = engine, upload_dir, info
        self.pool = ThreadPoolExecutor(max_workers=1, thread_name_prefix="frames")
        self.thumb_pool = ThreadPoolExecutor(
            max_workers=1, thread_name_prefix="thumbs", initializer=lower_priority
        )
        self._thumbs = Recent(1024)  # material → PNG bytes (a few KB each)

    async def run(self, fn, *args, pool=None):
        return await asyncio.get_running_loop().run_in_executor(
            pool or self.pool, functools.partial(fn, *args)
        )

    def thumb(self, material_id: str) -> bytes:
        """The gallery picture: a stored material's render under its first sun, a file
        material's colour map (:mod:`trainer.rendering.viewer.thumbs`), or else its diffuse map."""
        body = self._thumbs.get(material_id)
        if body is None:
            body = _png(self._thumb_image(material_id))
            self._thumbs.put(material_id, body)
        return body

    def _thumb_image(self, material_id: str) -> Image.Image:
        lib = self.engine.library
        e = lib.entry(material_id)
        if e.store is not None:
            pic = Image.fromarray(to_uint8(tonemap(lib.truth(material_id, 0)[0])))
        else:
            pic = colour_preview(e.path, THUMB) if e.path is not None else None
            if pic is None:
                pic = Image.fromarray(lib.textures(material_id)[:3].permute(1, 2, 0).numpy())
        pic.thumbnail((THUMB, THUMB))
        return pic

    def close(self) -> None:
        self.thumb_pool.shutdown(wait=False, cancel_futures=True)
        self.pool.shutdown(wait=False, cancel_futures=True)
        shutil.rmtree(self.upload_dir, ignore_errors=True)


def lower_priority() -> None:
    """This thread yields the CPU to the rest of the process: nice ``THUMB_NICE`` above it
    (Linux gives each thread its own nice value; elsewhere a no-op). The gallery's pictures
    are made on such a thread, so they still come while a frame is in the works, but they
    do not slow that frame where the cores are few."""
    if not sys.platform.startswith("linux"):
        return
    tid = threading.get_native_id()
    with contextlib.suppress(OSError):
        os.setpriority(os.PRIO_PROCESS, tid, os.getpriority(os.PRIO_PROCESS, tid) + THUMB_NICE)


def _png(pic: Image.Image) -> bytes:
    buf = io.BytesIO()
    pic.save(buf, format="PNG")
    return buf.getvalue()


def _error(status: int, message: str) -> web.Response:
    return web.json_response({"error": message.splitlines()[0] if message else "error"},
                             status=status)  # fmt: skip


class Handlers:
    """The viewer's request handlers, a method each; ``secret`` goes into the page for its
    uploads (:func:`shaderball.web.application`)."""

    def __init__(self, viewer: Viewer, secret: str):
        self.viewer, self.secret, self.engine = viewer, secret, viewer.engine

    async def index(self, request):
        materials = self.engine.library.listing()
        text = page.render(secret=self.secret, info=self.viewer.info, materials=materials)
        return web.Response(text=text, content_type="text/html")

    async def materials(self, request):
        return web.json_response(self.engine.library.listing())

    async def thumb(self, request):
        try:
            m = request.query.get("m", "")
            body = await self.viewer.run(self.viewer.thumb, m, pool=self.viewer.thumb_pool)
        except MaterialError as exc:
            return _error(404, str(exc))
        return web.Response(body=body, content_type="image/png")

    async def frame(self, request):
        q = request.query
        try:
            edits, light = Edits.from_query(q), Light.from_query(q)
            m, fmt = q.get("m", ""), q.get("fmt", "jpeg")
            f = await self.viewer.run(self.engine.frame, m, edits, light, fmt)
        except (MaterialError, ValueError) as exc:
            return _error(400, str(exc))
        headers = {"Server-Timing": f.server_timing(), "Cache-Control": "no-store"}
        if q.get("download"):
            name = _download_name(self.engine.library.entry(q["m"]).label, light)
            headers["Content-Disposition"] = f'attachment; filename="{name}"'
        return web.Response(body=f.body, content_type=f.content_type, headers=headers)

    async def truth(self, request):
        try:
            k = int(request.query.get("k", ""))
            out = await self.viewer.run(self.engine.truth, request.query.get("m", ""), k)
        except (MaterialError, ValueError) as exc:
            return _error(400, str(exc))
        for key in ("truth", "network", "error"):
            out[key] = "data:image/png;base64," + base64.b64encode(out[key]).decode()
        return web.json_response(out)

    async def upload(self, request):
        lib = self.engine.library
        incoming = Path(tempfile.mkdtemp(prefix="incoming-", dir=self.viewer.upload_dir))
        try:
            files = await _receive_files(request, lib.max_upload_bytes, incoming)
            entry = await self.viewer.run(lib.add_upload, files)
        except _TooLarge as exc:
            return _error(413, str(exc))
        except (MaterialError, ValueError) as exc:
            return _error(400, str(exc))
        finally:
            shutil.rmtree(incoming, ignore_errors=True)
        return web.json_response(entry.to_dict())


def make_app(viewer: Viewer, token: str | None) -> web.Application:
    app, secret = application(token)
    h = Handlers(viewer, secret)
    app.add_routes(
        [
            web.get("/", h.index),
            web.get("/api/materials", h.materials),
            web.get("/api/thumb", h.thumb),
            web.get("/api/frame", h.frame),
            web.get("/api/truth", h.truth),
            web.post("/api/upload", h.upload),
        ]
    )

    async def cleanup(app):
        viewer.close()

    app.on_cleanup.append(cleanup)
    return app


def _download_name(label: str, light: Light) -> str:
    """A frame's file name: the material's label, safe in a path, and its sun."""
    safe = re.sub(r"[^A-Za-z0-9._-]+", "_", label)[:60]
    return f"shaderball-{safe}-az{light.azimuth:.0f}-el{light.elevation:.0f}.png"


class _TooLarge(ValueError):
    pass


async def _receive_files(request: web.Request, limit: int, folder: Path) -> list[tuple[str, Path]]:
    """The uploaded files of a multipart request, each written into ``folder`` as it comes
    (never held whole in memory), with their names; raises as soon as they pass ``limit``
    bytes together."""
    if not request.content_type.startswith("multipart/"):
        raise ValueError("expected a multipart/form-data upload of image files")
    reader = await request.multipart()
    files, total = [], 0
    while (part := await reader.next()) is not None:
        if not part.filename:
            continue
        path = folder / str(len(files))
        with path.open("wb") as out:
            while chunk := await part.read_chunk(1 << 20):
                total += len(chunk)
                if total > limit:
                    raise _TooLarge(f"upload is over the viewer's {limit >> 20} MB limit")
                out.write(chunk)
        files.append((part.filename, path))
    if not files:
        raise ValueError("no file uploaded")
    return files


def build(
    checkpoint: str,
    stores: list[str],
    folders: list[str],
    device: str,
    max_upload_bytes: int = MAX_UPLOAD_BYTES,
    graph: bool = False,
) -> tuple[Viewer, list[str]]:
    """The viewer of ``checkpoint`` with its gallery; returns it and notes for the console.
    ``graph``: frames through the CUDA graph (:class:`trainer.rendering.infer.Renderer`)."""

    renderer = load_renderer(checkpoint, device, graph=graph)
    notes = []
    try:
        mapper = material_mapper(renderer, stores[0] if stores else None)
    except NoScreenUV as exc:
        mapper = None
        notes.append(f"only stored materials can be shown: {exc}")
    upload_dir = Path(tempfile.mkdtemp(prefix="shaderball-viewer-"))
    try:
        library = Library(stores, folders, upload_dir, max_upload_bytes)
        for i, store in enumerate(library.stores):
            if store.layout.resolution != renderer.config.resolution:
                raise ValueError(
                    f"{stores[i]}: its renders are {store.layout.resolution}², the network's "
                    f"{renderer.config.resolution}²"
                )
    except BaseException:
        shutil.rmtree(upload_dir, ignore_errors=True)
        raise
    info = {
        "checkpoint": checkpoint,
        "step": renderer.step,
        "weights": renderer.weights,  # "average": the run's moving average (--ema-decay)
        "resolution": renderer.config.resolution,
        "model": renderer.config.arch,
        "device": f"{renderer.device} · {renderer.runtime}",
        "mapping": mapper is not None,
        "stores": list(stores),
    }
    label = checkpoint if renderer.step is None else f"{checkpoint} (step {renderer.step})"
    engine = Engine(renderer, mapper, library, label)
    return Viewer(engine, upload_dir, info), notes
