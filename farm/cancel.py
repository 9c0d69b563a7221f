"""Cancelling a running farm job: a request file the driver polls.

``farm cancel STORE`` (or the dashboard's button) puts ``<store>/farm/cancel.json``. The
driver reads it every few seconds (:data:`farm.driver.STATE_EVERY_S`); then it stops
dispatching, lets the tasks in flight finish, commits every shard that is whole, records the
job as ``cancelled`` and exits 0. Materials of shards left incomplete are rendered again by the
next ``farm submit`` of the same command, which resumes, and which clears the request first.
"""

from __future__ import annotations

import json
import os
import socket
import time

from storage.backend import Backend

CANCEL_KEY = "farm/cancel.json"


def request_cancel(backend: Backend, by: str = "") -> dict:
    """Ask the job's driver to stop; returns the request."""
    rec = {"by": by or f"{socket.gethostname()}:{os.getpid()}", "at": time.time()}
    backend.put_atomic(CANCEL_KEY, json.dumps(rec).encode())
    return rec


def cancel_requested(backend: Backend) -> dict | None:
    raw = backend.get(CANCEL_KEY)
    if raw is None:
        return None
    try:
        return json.loads(raw)
    except json.JSONDecodeError:
        return {"by": "?", "at": 0.0}


def clear_cancel(backend: Backend) -> None:
    backend.delete(CANCEL_KEY)
