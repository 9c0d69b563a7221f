"""A fault-injecting HTTP proxy on 127.0.0.1, in front of the tests' S3 server.

Every ``every``-th request (of the HTTP ``methods`` given; all when none) gets a fault, taking
turns: a 503 ``SlowDown`` answer (S3's throttling), a connection reset before any answer, and a
stall of ``stall_s`` (longer than the client's read timeout) before the request goes through
(``stall_s`` 0: no stalls). A 503 or reset fault hits the same request (method, path and
query) for ``burst`` tries in a row and for ``hold_s`` seconds, whichever lasts longer, as S3
throttles one prefix for a while. The window is what makes a fault outlast the quick retries
of every client that asks at once: two DataLoader workers open the same array's metadata
together, and a count of tries alone would be shared between them, each seeing fewer
failures than s3fs absorbs (``S3FS_TRIES``; botocore's retries are turned off in the tests).
With both above what s3fs makes itself, the fault reaches this project's retry policy
whatever else is in flight (:meth:`FlakyProxy.past_client_retries`). ``limit``: at most that
many requests start a fault (None: no limit), so that an operation of many requests, retried
whole, ends. Faulting only ``GET`` or ``PUT`` keeps clear of the requests s3fs answers another
way when they fail (a failed ``HEAD`` falls back to a listing). All other requests are forwarded.
``deny``: a path fragment answered with 403 ``AccessDenied`` every time (a permanent error).
"""

from __future__ import annotations

import asyncio
import itertools
import threading
import time

import aiohttp
import s3fs
from aiohttp import web

HOP = {"connection", "keep-alive", "transfer-encoding", "content-length", "host"}
SLOW_DOWN = (
    b'<?xml version="1.0" encoding="UTF-8"?><Error><Code>SlowDown</Code>'
    b"<Message>Please reduce your request rate.</Message></Error>"
)
#: how often s3fs tries a request itself before it raises
S3FS_TRIES = s3fs.S3FileSystem.retries
#: seconds from s3fs's first try of a request to its last: it sleeps ``0.1 * 1.7**i`` after
#: try ``i`` (s3fs.core._error_wrapper)
S3FS_SPAN_S = sum(min(1.7**i * 0.1, 15) for i in range(S3FS_TRIES - 1))
DENIED = (
    b'<?xml version="1.0" encoding="UTF-8"?><Error><Code>AccessDenied</Code>'
    b"<Message>Access Denied</Message></Error>"
)


class FlakyProxy:
    def __init__(
        self,
        upstream: str,
        every: int = 7,
        stall_s: float = 4.0,
        deny: str = "",
        burst: int = 1,
        limit: int | None = None,
        methods: tuple[str, ...] = (),
        hold_s: float = 0.0,
    ):
        self.upstream, self.every, self.stall_s, self.deny = upstream, every, stall_s, deny
        self.burst, self.limit, self.methods, self.hold_s = burst, limit, methods, hold_s
        self.matching = self.started = 0  # requests that may fault; faults started
        #: request -> (fault, tries left to fault, time.monotonic() to fault until)
        self.pending: dict[str, tuple[str, int, float]] = {}
        self.count = itertools.count(1)
        self.faults = {"503": 0, "reset": 0, "stall": 0, "denied": 0}
        self.requests = 0
        self.loop = asyncio.new_event_loop()
        self.port = 0
        self._ready = threading.Event()
        self._thread = threading.Thread(target=self._serve, daemon=True)

    @classmethod
    def past_client_retries(
        cls, upstream: str, every: int, method: str, deny: str = ""
    ) -> FlakyProxy:
        """Faults that reach this project's retry policy: one ``method`` request in ``every``
        fails (503 or reset, no stalls) for more tries than s3fs makes, and for twice the
        time its tries take (so for every client that asks within a second of the first), at
        most 4 of them."""
        return cls(
            upstream, every, stall_s=0, deny=deny, burst=S3FS_TRIES + 1, limit=4,
            methods=(method,), hold_s=2 * S3FS_SPAN_S + 0.5,
        )  # fmt: skip

    @property
    def endpoint(self) -> str:
        return f"http://127.0.0.1:{self.port}"

    def __enter__(self) -> FlakyProxy:
        self._thread.start()
        self._ready.wait(10)
        return self

    def __exit__(self, *exc) -> None:
        for done in (self.runner.cleanup(), self.session.close()):  # open keep-alives too
            asyncio.run_coroutine_threadsafe(done, self.loop).result(10)
        self.loop.call_soon_threadsafe(self.loop.stop)
        self._thread.join(10)

    def _serve(self) -> None:
        asyncio.set_event_loop(self.loop)
        app = web.Application(client_max_size=1 << 30)
        app.router.add_route("*", "/{tail:.*}", self._handle)
        self.runner = runner = web.AppRunner(app)
        self.loop.run_until_complete(runner.setup())
        site = web.TCPSite(runner, "127.0.0.1", 0)
        self.loop.run_until_complete(site.start())
        self.port = site._server.sockets[0].getsockname()[1]
        self.session = self.loop.run_until_complete(self._session())
        self._ready.set()
        self.loop.run_forever()

    async def _session(self) -> aiohttp.ClientSession:
        return aiohttp.ClientSession(auto_decompress=False)

    def _fault(self, method: str, key: str) -> str | None:
        """The fault for a ``method`` request that ``key`` names (None: forward it)."""
        if key in self.pending:
            kind, left, until = self.pending.pop(key)
            if left > 0 or time.monotonic() < until:
                self.pending[key] = (kind, left - 1, until)
                return kind
        if self.methods and method not in self.methods:
            return None
        self.matching += 1
        if self.matching % self.every or (self.limit is not None and self.started >= self.limit):
            return None
        kinds = ("503", "reset", "stall") if self.stall_s else ("503", "reset")
        kind, self.started = kinds[self.started % len(kinds)], self.started + 1
        if kind != "stall" and (self.burst > 1 or self.hold_s > 0):
            self.pending[key] = (kind, self.burst - 1, time.monotonic() + self.hold_s)
        return kind

    async def _handle(self, request: web.Request) -> web.StreamResponse:
        n = next(self.count)
        self.requests = n
        body = await request.read()
        if self.deny and self.deny in request.path:
            self.faults["denied"] += 1
            return web.Response(status=403, body=DENIED, content_type="application/xml")
        kind = self._fault(request.method, f"{request.method} {request.path_qs}")
        if kind is not None:
            self.faults[kind] += 1
            if kind == "503":
                return web.Response(status=503, body=SLOW_DOWN, content_type="application/xml")
            if kind == "reset":
                request.transport.abort()
                raise asyncio.CancelledError
            await asyncio.sleep(self.stall_s)
        headers = {k: v for k, v in request.headers.items() if k.lower() not in HOP}
        url = self.upstream + request.path_qs
        async with self.session.request(
            request.method, url, headers=headers, data=body, allow_redirects=False
        ) as up:
            data = await up.read()
            out = {k: v for k, v in up.headers.items() if k.lower() not in HOP}
            response = web.Response(status=up.status, body=data, headers=out)
            if request.method == "HEAD" and "Content-Length" in up.headers:
                response.headers["Content-Length"] = up.headers["Content-Length"]
            return response
