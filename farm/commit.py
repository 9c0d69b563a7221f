"""Writing a finished shard where its data is, not in the driver.

A render worker returns two Ray objects per material: a small report the driver reads, and
the packed arrays (about 6.5 MB at 400² with five suns), which the driver never fetches. When
a shard's materials are all rendered, the driver starts :func:`commit_shard` as a Ray task
with the shard's array objects as arguments: Ray moves them from the workers' object stores
to the task's node (by default the node that already holds most of them), and the task writes
the shard and its commit record with ``storage.writer.write_shard``. The driver's work per
frame is then a few small messages, whatever the resolution.

Where the task may run: a store on an object store (``s3://``) is reachable from every node,
so anywhere; a local path only from the driver's machine, so there (:func:`placement`).
Worker nodes need the same object-store credentials as the driver (the environment that
fsspec/botocore read, e.g. ``AWS_*`` from one Secret on every pod).

Exactly once: the driver holds the store's lease (:mod:`farm.lease`) and submits each shard's
commit once; Ray re-runs the task only if its process died. A re-run that finds the shard
already committed is that same task's earlier attempt, which got as far as the commit record,
so it reports the existing record instead of failing.
"""

from __future__ import annotations

import logging
import os
import socket
import time

from storage.backend import is_remote
from storage.convert import payload_from_packed
from storage.errors import ShardCommittedError
from storage.reader import Store
from storage.retry import log as storage_log
from storage.writer import write_shard

#: object-store retry messages a commit reports back to the driver, at most
MAX_RETRY_LINES = 20


class _Lines(logging.Handler):
    """Collects the storage retry warnings logged while one shard is written."""

    def __init__(self):
        super().__init__(logging.WARNING)
        self.lines: list[str] = []

    def emit(self, record: logging.LogRecord) -> None:
        if len(self.lines) < MAX_RETRY_LINES:
            self.lines.append(record.getMessage())


def commit_shard(
    url: str, storage_options: dict | None, shard: int, records: list[dict], *packed: dict
) -> dict:
    """Write ``shard`` of the store at ``url`` from its materials' packed results (in material
    order; ``storage.convert.pack_material`` dicts) and ``records`` (``kind``, ``source_id``,
    ``spec`` each). Returns a small report: ``shard``, ``bytes`` stored, ``seconds``, ``host``,
    ``pid``, ``again`` (the shard was already committed by an earlier run of this task) and
    ``retries`` (the object-store retries it logged)."""
    t0 = time.perf_counter()
    lines = _Lines()
    storage_log.addHandler(lines)
    try:
        store = Store(url, storage_options)
        payload = payload_from_packed(store.layout, shard, list(packed), records)
        try:
            record, again = write_shard(store, shard, payload), False
        except ShardCommittedError:
            record, again = store.commit_record(shard), True
    finally:
        storage_log.removeHandler(lines)
    return {
        "shard": shard,
        "bytes": sum(record["files"].values()),
        "seconds": time.perf_counter() - t0,
        "host": socket.gethostname(),
        "pid": os.getpid(),
        "again": again,
        "retries": lines.lines,
    }


def placement(url: str) -> str:
    """Where a shard of the store at ``url`` may be written: ``anywhere`` (object stores) or
    ``driver`` (a local path, which only the driver's machine is known to see)."""

    return "anywhere" if is_remote(url) else "driver"
