"""Joining Ray: the environment Ray reads at import, the checks a job makes of its cluster
before anything is written, and ``ray.init`` itself.

A job with an address (``--address`` or ``RAY_ADDRESS``) checks, in order, that:

1. something accepts a connection there within :data:`REACH_TIMEOUT_S` (Ray itself would
   retry without end, printing only warnings), and it speaks gRPC: a web server there (the
   dashboard's port given for the GCS's, say) is refused at once, where Ray's client would
   wait out its own long timeout for it (:func:`not_grpc`);
2. the cluster's GCS accepts this driver's credentials. ``ray start`` (Ray 2.60) turns
   token authentication on when ``RAY_AUTH_MODE`` is not set and a token is at hand
   (``RAY_AUTH_TOKEN``, ``RAY_AUTH_TOKEN_PATH`` or ``~/.ray/auth_token``, which any local
   Ray writes, the embedded one included), while a driver joining a cluster sends no token
   unless ``RAY_AUTH_MODE=token``. So the driver follows ``ray start``'s rule: with a token
   at hand and ``RAY_AUTH_MODE`` not set, it sends it (a cluster without authentication
   ignores it);
3. for an address on the loopback interface, a live node of the cluster runs on this machine
   (within :data:`NODE_WAIT_S`), and which address it has: the driver joins that node
   (``_node_ip_address``). A cluster
   started by ``ray start --head`` has the machine's outward address, one started with
   ``--node-ip-address 127.0.0.1`` the loopback one; either is reached as 127.0.0.1.

Each failure is one :class:`ConnectionError` line that names the address and what to do.
"""

from __future__ import annotations

import contextlib
import logging
import os
import socket
import sys
import time
from pathlib import Path

from shaderball.web import is_loopback

#: how long a job waits for its Ray address to accept a connection
REACH_TIMEOUT_S = 10.0
#: how long the GCS has to list the cluster's nodes
GCS_TIMEOUT_S = 10.0
#: how long the server at a Ray address has to answer the HTTP/2 greeting
GREETING_TIMEOUT_S = 5.0
#: what an HTTP/2 client sends first (RFC 9113 3.4): the preface, then a SETTINGS frame (an
#: empty one: a 9-byte frame header of length 0, type 4, no flags, stream 0)
HTTP2_PREFACE = b"PRI * HTTP/2.0\r\n\r\nSM\r\n\r\n" + bytes([0, 0, 0, 4, 0, 0, 0, 0, 0])
#: the level of Ray's own logger in the driver: its start-up lines (the dashboard's address,
#: the cluster joined) say again what the job prints itself
QUIET = logging.WARNING
#: how long a job waits for a live node of its cluster on this machine: a head's GCS answers
#: seconds before its own node has joined (more on a busy machine), and Ray waits
#: as long for a local node before it gives up
NODE_WAIT_S = 60.0


def address_is_loopback(address: str | None) -> bool:
    """Whether a Ray address is on this machine's loopback interface (``None``: the embedded
    Ray); the host is read as :func:`endpoint` reads it, ``[::1]:6379`` included."""
    if not address:
        return True
    target = endpoint(address)
    return is_loopback(target[0] if target else address.split("://")[-1])


def token_at_hand(env=os.environ, home: Path | None = None) -> bool:
    """Whether Ray would find an authentication token here: ``RAY_AUTH_TOKEN``, a readable
    non-empty ``RAY_AUTH_TOKEN_PATH``, or ``~/.ray/auth_token`` (Ray's order)."""
    if env.get("RAY_AUTH_TOKEN"):
        return True
    path = env.get("RAY_AUTH_TOKEN_PATH")
    path = Path(path) if path else (home or Path.home()) / ".ray" / "auth_token"
    try:
        return bool(path.read_text().strip())
    except OSError:
        return False


def ray_environment(address: str | None) -> None:
    """What Ray reads from the environment once, when ``ray`` is imported, for a job at
    ``address`` (``None``: ``RAY_ADDRESS``, else the embedded Ray). For the embedded Ray and
    clusters on 127.0.0.1, ``RAY_ENABLE_WINDOWS_OR_OSX_CLUSTER=0``: Ray on Linux rewrites a
    loopback address to the machine's outward IP otherwise. ``RAY_AUTH_MODE=token`` (unless
    the environment sets it; ``disabled`` opts out) for the embedded Ray, Ray's own default
    for a new local cluster, said explicitly so that Ray does not warn that it chose it; and
    for a cluster when a token is at hand (the module docstring)."""
    if "ray" in sys.modules:
        return
    address = address or os.environ.get("RAY_ADDRESS")
    if address_is_loopback(address):
        os.environ.setdefault("RAY_ENABLE_WINDOWS_OR_OSX_CLUSTER", "0")
    if not address or token_at_hand():
        os.environ.setdefault("RAY_AUTH_MODE", "token")


def endpoint(address: str) -> tuple[str, int] | None:
    """The ``(host, port)`` that must answer at a Ray address: ``host:port`` (the GCS) or
    ``ray://host[:port]`` (the client server, port 10001 unless given); ``None`` for a form
    Ray resolves itself (``auto``, ``local``)."""
    scheme, _, rest = address.rpartition("://")
    if scheme not in ("", "ray"):
        return None
    host, sep, port = rest.rpartition(":")
    if not sep:
        host, port = rest, "10001" if scheme == "ray" else ""
    if not host or not port.isdigit():
        return None
    return host.strip("[]"), int(port)


def address_in_force(address: str | None) -> tuple[str | None, str]:
    """The address in force and what set it, as an error names it."""
    named = address or os.environ.get("RAY_ADDRESS") or None
    return named, "--address" if address else "RAY_ADDRESS"


def check_reachable(address: str | None, timeout_s: float = REACH_TIMEOUT_S) -> None:
    """Raise ``ConnectionError`` naming the address when nothing there accepts a connection
    within ``timeout_s``. ``None``: ``RAY_ADDRESS``, or the embedded Ray (nothing to check)."""
    named, source = address_in_force(address)
    target = endpoint(named) if named else None
    if target is None:
        return
    deadline = time.monotonic() + timeout_s
    while True:
        try:
            with socket.create_connection(target, timeout=min(5.0, timeout_s)):
                return
        except OSError as exc:
            if time.monotonic() >= deadline:
                why = exc.strerror or type(exc).__name__
                raise ConnectionError(
                    f"{source} {named}: nothing answers there ({why}, for {timeout_s:.0f} s); "
                    "is the Ray cluster up, and is that its address?"
                ) from None
            time.sleep(0.5)


def not_grpc(target: tuple[str, int], timeout_s: float = GREETING_TIMEOUT_S) -> str | None:
    """What answers at ``target`` when it is surely not a gRPC server (a GCS and Ray's client
    server are), as words for an error; ``None`` for an HTTP/2 server, and when nothing is
    sure (no connection, no answer in time): Ray's own client then decides.

    An HTTP/2 server answers a client's preface with a SETTINGS frame first (RFC 9113 3.4).
    The bytes are read by hand because grpc's channel states tell a server that answers
    something else only from one that is slow, after the same wait."""
    try:
        with socket.create_connection(target, timeout=timeout_s) as conn:
            conn.sendall(HTTP2_PREFACE)
            head = b""
            while len(head) < 9:
                chunk = conn.recv(9 - len(head))
                if not chunk:
                    break
                head += chunk
    except OSError:  # refused, reset or silent: not sure
        return None
    if len(head) == 9 and head[3] == 4:  # a frame header, of type SETTINGS
        return None
    if head.startswith((b"HTTP/", b"<")):  # a status line, or an old-style bare page
        return "a web server answers there, not Ray"
    if not head:
        return "the server there closed the connection without a gRPC greeting"
    return "the server there does not speak gRPC, as Ray's servers do"


def driver_node(address: str, nodes: list[str], local: set[str]) -> str:
    """The node address a driver joins a cluster at the loopback ``address`` as, from the
    addresses of the cluster's live ``nodes`` and this machine's ``local`` addresses: a
    loopback node first, then one with an address of this machine. ``ValueError`` when no
    node runs here (the driver needs one of the cluster's nodes on its own machine)."""
    for ip in [n for n in nodes if is_loopback(n)] + [n for n in nodes if n in local]:
        return ip
    listed = ", ".join(sorted(set(nodes))) or "none alive"
    raise ValueError(
        f"{address}: no node of that Ray cluster runs on this machine (its nodes: {listed}); "
        "run the job on one of them, or join through Ray's client (ray://HEAD:10001)"
    )


@contextlib.contextmanager
def _stderr_silenced():
    """File descriptor 2 to /dev/null for the block: Ray's C++ GCS client logs a refused
    token there, beside the one-line error the job prints itself."""
    sys.stderr.flush()
    saved = os.dup(2)
    try:
        with open(os.devnull, "w") as null:
            os.dup2(null.fileno(), 2)
        yield
    finally:
        os.dup2(saved, 2)
        os.close(saved)


def live_nodes(gcs: str) -> list[str]:
    """The addresses of the live nodes of the cluster whose GCS is at ``gcs``.
    ``ray.exceptions.AuthenticationError`` when it refuses this driver's credentials."""
    # Ray's own GCS client: the public ways to list nodes need ray.init or the dashboard
    from ray._raylet import GcsClient
    from ray.core.generated.gcs_pb2 import GcsNodeInfo

    with _stderr_silenced():
        info = GcsClient(address=gcs).get_all_node_info(timeout=GCS_TIMEOUT_S)
    return [n.node_manager_address for n in info.values() if n.state == GcsNodeInfo.ALIVE]


def check_speaks_grpc(named: str | None, source: str, target: tuple[str, int] | None) -> None:
    """``ConnectionError`` when the server at a Ray address surely is not a GCS or Ray's
    client server (:func:`not_grpc`). Not asked under ``RAY_USE_TLS``, where a plain
    greeting gets a TLS alert from a real one."""
    if target is None or os.environ.get("RAY_USE_TLS", "0").lower() in ("1", "true"):
        return
    why = not_grpc(target)
    if why:
        wanted = (
            "Ray's client server (ray://HEAD:10001)"
            if named.startswith("ray://")
            else "the GCS (HEAD:6379 unless `ray start --port` said otherwise)"
        )
        raise ConnectionError(f"{source} {named}: {why}; give the address of {wanted}")


def check_cluster(address: str | None) -> str | None:
    """The checks of the module docstring, before anything is written; returns the node
    address the driver joins as (``None``: Ray's choice). ``ConnectionError`` on failure."""
    check_reachable(address)
    named, source = address_in_force(address)
    target = endpoint(named) if named else None
    check_speaks_grpc(named, source, target)
    if named is None or target is None or "://" in named:  # embedded, auto, ray:// client
        return "127.0.0.1" if address_is_loopback(named) else None
    nodes = _nodes(named, source)
    if not address_is_loopback(named):
        return None
    import psutil

    local = {a.address for addrs in psutil.net_if_addrs().values() for a in addrs}
    deadline = time.monotonic() + NODE_WAIT_S
    while True:
        try:
            return driver_node(f"{source} {named}", nodes, local)
        except ValueError as exc:
            if time.monotonic() >= deadline:
                raise ConnectionError(str(exc)) from None
        time.sleep(0.5)
        nodes = _nodes(named, source)


def _nodes(gcs: str, source: str) -> list[str]:
    """:func:`live_nodes`; a refusal of the driver's credentials, or no GCS there, as one
    line."""
    from ray.exceptions import AuthenticationError, RayError

    try:
        return live_nodes(gcs)
    except AuthenticationError:
        sent = os.environ.get("RAY_AUTH_MODE") == "token"
        raise ConnectionError(
            f"{source} {gcs}: the Ray cluster refused this driver's "
            + ("token; give it the cluster's " if sent else "request without a token; give it ")
            + "token in RAY_AUTH_TOKEN or ~/.ray/auth_token (`ray get-auth-token` on its head "
            "prints it)"
        ) from None
    except RayError as exc:  # something answers, but not a Ray cluster's GCS
        first = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
        raise ConnectionError(f"{source} {gcs}: no Ray cluster answers there ({first})") from None


def connect(address: str | None, dashboard: bool = True, node: str | None = None) -> str | None:
    """Join the Ray cluster at ``address`` (or ``RAY_ADDRESS``) as the node at ``node``
    (:func:`check_cluster`'s answer), else start an embedded one (with its dashboard unless
    ``dashboard`` is false). Returns the dashboard URL."""
    import ray

    address, _ = address_in_force(address)
    if address:
        extra = {"_node_ip_address": node} if node else {}
        ctx = ray.init(address=address, log_to_driver=False, logging_level=QUIET, **extra)
    else:
        ctx = ray.init(  # embedded: everything on the loopback interface
            # a new local Ray, even when a cluster started with `ray start` runs here (with
            # no address Ray would join that one)
            address="local",
            num_cpus=os.cpu_count(),
            include_dashboard=dashboard,
            log_to_driver=False,
            logging_level=QUIET,
            _node_ip_address="127.0.0.1",
            dashboard_host="127.0.0.1",
            # Ray runs its workers at nice 15 by default; here the renders are the work
            _system_config={"worker_niceness": 0},
        )
    url = getattr(ctx, "dashboard_url", None)
    return f"http://{url}" if url and not url.startswith("http") else url
