"""One live driver per store: a lease in ``<store>/farm/lease.json`` that the driver renews.

A driver takes the lease before it renders and renews it with every job-state save. A second
``farm submit`` on the store refuses while the lease is live, naming the holder (host, pid,
last renewal). A lease is dead once it is ``LEASE_S`` old, or at once when its driver ran on
this machine and that process is gone (a killed driver is resumed by resubmitting, as before).

Taking it on a local store (a path, a shared filesystem's included) is read-check-write under
an exclusive ``flock`` on the store's ``farm`` folder: of two drivers started together the
second sees the first's live lease and refuses. Where that lock cannot be had (an object store;
a filesystem without ``flock``) it is write-then-read-back: the driver writes its lease, waits
``SETTLE_S`` and reads it back, and of two drivers started together the last writer keeps it.
That is not a consensus lock (a write delayed past the settle time could let both through),
but the store itself stays safe then: shards are written whole and committed once, and a
second commit of a shard is refused.
"""

from __future__ import annotations

import contextlib
import fcntl
import json
import os
import socket
import time
import uuid
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import psutil

from shaderball.errors import UserError
from storage.backend import Backend

LEASE_KEY = "farm/lease.json"
#: a lease not renewed for this long is dead (the driver renews it every couple of seconds)
LEASE_S = 30.0
#: how long a new driver waits before reading its lease back
SETTLE_S = 1.5


class LeaseHeld(UserError, RuntimeError):
    """Another driver holds the store's lease."""


def _me() -> dict:
    return {
        "host": socket.gethostname(),
        "pid": os.getpid(),
        "started": psutil.Process().create_time(),
    }


def read_lease(backend: Backend) -> dict | None:
    """The store's lease record, or ``None`` when no driver holds or held one."""
    raw = backend.get(LEASE_KEY)
    return json.loads(raw) if raw else None


def holder_alive(rec: dict, now: float, here: str | None = None) -> bool:
    """Whether the lease ``rec`` still binds: renewed within ``LEASE_S``, and, when its
    driver ran on this host (``here``), that very process still running (the same process:
    its start time, where the record has it)."""
    if now - rec.get("renewed", 0.0) > LEASE_S:
        return False
    if rec.get("host") != (here or socket.gethostname()) or rec.get("pid") is None:
        return True
    try:
        started = psutil.Process(rec["pid"]).create_time()
    except psutil.NoSuchProcess:
        return False
    return rec.get("started") is None or started == rec["started"]


def describe(url: str, rec: dict, now: float) -> str:
    ago = max(now - rec.get("renewed", now), 0.0)
    return (
        f"{url}: another farm submit is running on this store (driver {rec.get('host')}:"
        f"{rec.get('pid')}, lease renewed {ago:.0f} s ago); let it finish or stop it, then "
        "run the same command again to resume"
    )


@dataclass
class Lease:
    url: str
    backend: Backend
    record: dict

    def _read(self) -> dict | None:
        return read_lease(self.backend)

    def _write(self) -> None:
        self.record["renewed"] = time.time()
        self.backend.put_atomic(LEASE_KEY, json.dumps(self.record).encode())

    def renew(self) -> None:
        self._write()

    def release(self) -> None:
        """Give the lease up, if it is still this driver's."""
        rec = self._read()
        if rec is not None and rec.get("token") == self.record["token"]:
            self.backend.delete(LEASE_KEY)


@contextlib.contextmanager
def _locked(backend: Backend) -> Iterator[bool]:
    """Hold an exclusive ``flock`` on a local store's ``farm`` folder for the block; yields
    whether it is held (False for an object store, or where ``flock`` fails)."""
    if not backend.local:
        yield False
        return
    folder = Path(backend.path(LEASE_KEY)).parent
    folder.mkdir(parents=True, exist_ok=True)
    fd = os.open(folder, os.O_RDONLY)
    try:
        try:
            fcntl.flock(fd, fcntl.LOCK_EX)
        except OSError:  # an NFS mount may refuse it on a folder: read back after a settle
            yield False
            return
        yield True
    finally:
        os.close(fd)  # closing releases the lock


def acquire(url: str, backend: Backend, settle_s: float = SETTLE_S) -> Lease:
    """Take the store's lease or raise :class:`LeaseHeld` naming its holder."""
    lease = Lease(url, backend, {**_me(), "token": uuid.uuid4().hex})
    with _locked(backend) as locked:
        rec = lease._read()
        if rec is not None and holder_alive(rec, time.time()):
            raise LeaseHeld(describe(url, rec, time.time()))
        lease._write()
    if locked:
        return lease
    time.sleep(settle_s)
    rec = lease._read()
    if rec is None or rec.get("token") != lease.record["token"]:
        raise LeaseHeld(describe(url, rec or {}, time.time()))
    return lease
