"""The small web layer of this project's servers (``farm dashboard``, ``trainer viewer``):
aiohttp, bound to 127.0.0.1 unless told otherwise, a token on any other
address, a per-server secret on every POST, and files served only from inside given roots.

Rules every server built on it follows:

* **Binding.** ``--host`` defaults to 127.0.0.1. A non-loopback host needs a token: the one
  given, or one generated here and printed once. With a token, every request without it (as
  ``Authorization: Bearer``, the ``shaderball_token`` cookie, or ``?token=``, which sets the
  cookie) gets 401.
* **Host.** Without a token, only requests naming a loopback host (``127.0.0.1``,
  ``localhost``, ``[::1]``) are served (403 otherwise), so a web page whose domain is made to
  resolve to 127.0.0.1 (DNS rebinding) cannot read the pages.
* **POST.** A request that changes anything is a POST carrying the server's secret in the
  ``X-Shaderball-Secret`` header; the pages embed it. Another site's form cannot send it.
* **Files.** A path from a request names something under a root with :func:`confine`:
  absolute paths, ``..`` (after URL decoding) and symlinks that lead outside are refused.
* **Icon.** Every application answers ``/favicon.svg`` and ``/favicon.ico`` with the same
  small SVG shaderball (:data:`ICON_SVG`); pages link it with :data:`ICON_LINK`.
"""

from __future__ import annotations

import errno
import hmac
import ipaddress
import secrets
import socket
from pathlib import Path

import click

# aiohttp is imported where it is used: the command lines import this module for
# :func:`server_options` in every install, the server needs the [dashboard] extra

TOKEN_COOKIE = "shaderball_token"
ICON_LINK = '<link rel="icon" href="/favicon.svg" type="image/svg+xml">'
# a ball lit from the upper left on its stand: the tab icon of every page
ICON_SVG = (
    '<svg xmlns="http://www.w3.org/2000/svg" viewBox="0 0 32 32"><defs><radialGradient id="b" '
    'cx=".35" cy=".3" r=".8"><stop offset="0" stop-color="#fff6e0"/><stop offset=".3" '
    'stop-color="#e8a33c"/><stop offset="1" stop-color="#5a2e0c"/></radialGradient></defs>'
    '<rect x="10" y="25" width="12" height="6" rx="1.5" fill="#5c6370"/>'
    '<circle cx="16" cy="14" r="12" fill="url(#b)"/></svg>'
)
SECRET_HEADER = "X-Shaderball-Secret"


class Refused(ValueError):
    """A request path that would leave its root."""


def is_loopback(host: str) -> bool:
    if host == "localhost":
        return True
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:
        return False


def token_for(host: str, given: str | None, echo=print) -> str | None:
    """The token the server will require: ``given``; else, off loopback, a new one (printed
    once); else none."""
    if given:
        return given
    if is_loopback(host):
        return None
    token = secrets.token_urlsafe(24)
    echo(f"token (needed by every request from another machine): {token}")
    return token


def confine(root: Path, rel: str) -> Path:
    """``root / rel``, refused when ``rel`` is absolute, climbs with ``..``, or resolves
    (through symlinks) outside ``root``."""
    if rel.startswith(("/", "\\")) or "\\" in rel or "\x00" in rel:
        raise Refused(rel)
    if any(part == ".." for part in rel.split("/")):
        raise Refused(rel)
    base = root.resolve()
    path = (base / rel).resolve()
    if path != base and not path.is_relative_to(base):
        raise Refused(rel)
    return path


def confine_key(rel: str) -> str:
    """An object-store key below a prefix (``.``: the prefix itself), refused as
    :func:`confine` refuses paths."""
    if rel == ".":
        return rel
    if rel.startswith("/") or "\\" in rel or any(p in ("", "..") for p in rel.split("/")):
        raise Refused(rel)
    return rel


def server_options(port: int):
    """``--host``, ``--port`` (default ``port``) and ``--token``: the options of every server
    built on this layer."""

    def decorate(command):
        for option in reversed([
            click.option("--host", default="127.0.0.1", show_default=True,
                         help="Address to bind; any other than loopback needs a token."),
            click.option("--port", default=port, show_default=True,
                         type=click.IntRange(0, 65535), help="Port to listen on."),
            click.option("--token", envvar="SHADERBALL_TOKEN", default=None,
                         help="Token every request must carry (generated off loopback when "
                         "not given)."),
        ]):  # fmt: skip
            command = option(command)
        return command

    return decorate


def guard(token: str | None, secret: str):
    """Middleware: the token (when there is one) on every request, the secret on POSTs."""
    from aiohttp import web

    @web.middleware
    async def middleware(request: web.Request, handler):
        if token is None and not is_loopback((request.url.host or "").strip("[]")):
            return web.Response(status=403, text="403: this server answers loopback hosts only\n")
        if token is not None:
            given = request.query.get("token") or request.cookies.get(TOKEN_COOKIE) or ""
            auth = request.headers.get("Authorization", "")
            if auth.startswith("Bearer "):
                given = auth[7:]
            if not hmac.compare_digest(given.encode(), token.encode()):
                return web.Response(status=401, text="401: a token is needed (?token=...)\n")
        if request.method == "POST":
            sent = request.headers.get(SECRET_HEADER, "")
            if not hmac.compare_digest(sent.encode(), secret.encode()):
                return web.Response(status=403, text="403: missing or wrong secret\n")
        try:
            response = await handler(request)
        except Refused:
            return web.Response(status=404, text="404: outside the served folders\n")
        if token is not None and request.query.get("token") == token:
            response.set_cookie(TOKEN_COOKIE, token, httponly=True, samesite="Strict")
        return response

    return middleware


def application(token: str | None, **options):
    """A guarded ``aiohttp.web.Application`` answering the icon, and its POST secret
    (``options`` go to the application)."""
    from aiohttp import web

    async def icon(request):
        return web.Response(
            text=ICON_SVG, content_type="image/svg+xml", headers={"Cache-Control": "max-age=86400"}
        )

    secret = secrets.token_urlsafe(16)
    app = web.Application(middlewares=[guard(token, secret)], **options)
    app.add_routes([web.get("/favicon.svg", icon), web.get("/favicon.ico", icon)])
    return app, secret


def listen(host: str, port: int) -> socket.socket:
    """A socket listening on ``host:port`` (port 0: any free one); an unknown host or a taken
    port is a one-line error that names it."""
    try:
        info = socket.getaddrinfo(host, port, type=socket.SOCK_STREAM, flags=socket.AI_PASSIVE)
    except OSError as exc:
        raise click.ClickException(f"cannot listen on --host {host}: {exc.strerror}") from None
    family, kind, proto, _, address = info[0]
    sock = socket.socket(family, kind, proto)
    try:
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        sock.bind(address)
        sock.listen(128)
    except OSError as exc:
        sock.close()
        hint = " (another --port, or 0 for any free one)" if exc.errno == errno.EADDRINUSE else ""
        raise click.ClickException(
            f"cannot listen on {host}:{port}: {exc.strerror}{hint}"
        ) from None
    return sock


def serve(app, host: str, port: int, echo, name: str) -> None:
    """Run the aiohttp ``app`` on ``host:port`` until interrupted, after printing where."""
    from aiohttp import web

    sock = listen(host, port)
    shown = f"[{host}]" if ":" in host else host
    echo(f"{name}: http://{shown}:{sock.getsockname()[1]}/")
    web.run_app(app, sock=sock, print=None, access_log=None)
