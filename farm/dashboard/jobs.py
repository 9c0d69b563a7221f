"""What the dashboard knows of farm jobs, read only from what the farm persists: the job state
(``farm/job.json``), the commit records' listing, and the store. No Ray; a store that is
corrupt, half-written or not a store gives an ``error`` instead of a row's numbers.

A ROOT is a store, a folder of stores (searched two levels down), or an ``s3://`` prefix of
them. Stores are named ``<root index>/<path below the root>`` (``.``: the root itself) in
URLs, and labelled with the root as given plus that path (``out/demo.zarr``) on the pages and in
the metrics.
"""

from __future__ import annotations

import os
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from farm.state import load_state, window_rate
from shaderball.web import confine, confine_key
from storage.backend import Backend, is_remote
from storage.reader import Store
from storage.schema import COMMITS

#: a live worker that has not reported for this long is marked stale
STALE_S = 60.0
STATUSES = ("running", "done", "failed", "cancelled", "lost", "interrupted", "no state")


def label(root: str, rel: str) -> str:
    """What pages and metrics call the store or run ``rel`` below ``root``: the root as
    given on the command line, then the path (``out/demo.zarr``; ``.``: the root itself)."""
    if not is_remote(root):
        return os.path.normpath(os.path.join(root, rel))  # ``.``, ``out/``: as typed
    root = root.rstrip("/")
    return root if rel == "." else f"{root}/{rel}"


@dataclass(frozen=True)
class Root:
    index: int
    url: str

    @property
    def remote(self) -> bool:
        return is_remote(self.url)

    def store_url(self, rel: str) -> str:
        """The URL of store ``rel`` below this root (refused when it would leave it)."""
        if self.remote:
            rel = confine_key(rel)
            return self.url.rstrip("/") if rel == "." else f"{self.url.rstrip('/')}/{rel}"
        return str(confine(Path(self.url), rel))

    def find(self) -> list[str]:
        """Relative names of the stores under this root, sorted."""
        if Backend(self.url).get("zarr.json") is not None:
            return ["."]
        if self.remote:
            return self._find_remote()
        base = Path(self.url)
        if not base.is_dir():
            return []
        found = []
        for child in sorted(base.iterdir()):
            if (child / "zarr.json").exists():
                found.append(child.name)
            elif child.is_dir() and not child.name.startswith("."):
                found += [f"{child.name}/{g.name}" for g in sorted(child.iterdir())
                          if (g / "zarr.json").exists()]  # fmt: skip
        return found

    def _find_remote(self) -> list[str]:
        b = Backend(self.url)
        out = []
        for entry in sorted(b.fs.ls(b.root, detail=False)):
            name = entry.rstrip("/").rsplit("/", 1)[-1]
            if b.fs.exists(f"{entry.rstrip('/')}/zarr.json"):
                out.append(name)
        return out


def commit_times(backend: Backend) -> dict[int, float]:
    """Committed shards and when each was committed (the records' modification times), from
    one listing: no record is read."""
    out = {}
    if backend.local:
        try:
            entries = list(os.scandir(backend.path(COMMITS)))
        except FileNotFoundError:
            return {}
        for e in entries:
            if e.name.endswith(".json") and not e.name.startswith("."):
                out[int(e.name[:-5])] = e.stat().st_mtime
        return out
    path = backend.path(COMMITS)
    backend.fs.invalidate_cache(path)
    try:
        listing = backend.fs.ls(path, detail=True)
    except FileNotFoundError:
        return {}
    for e in listing:
        name = e["name"].rsplit("/", 1)[-1]
        if name.endswith(".json"):
            modified = e.get("LastModified")
            out[int(name[:-5])] = modified.timestamp() if modified is not None else 0.0
    return out


def job_row(name: str, url: str, label: str | None = None) -> dict:
    """One line of the jobs page (``error`` set when the store cannot be read); ``name`` is the
    store's key in URLs, ``label`` what the page shows (``name`` when not given)."""
    row = {"name": name, "label": label or name, "url": url, "error": None, "status": "no state"}
    try:
        state = load_state(url)
        store = Store(url)
    except Exception as exc:  # noqa: BLE001 - any damage shows on its row, not as a crash
        row["error"] = f"{type(exc).__name__}: {str(exc).splitlines()[0] if str(exc) else ''}"
        return row
    lay = store.layout
    row.update(frames_total=lay.num_samples, shards_total=lay.num_shards)
    if state is None:
        done = sum(len(lay.shard_samples(s)) for s in commit_times(store.backend))
        row.update(frames_done=done, frames_per_s=0.0, frames_per_s_now=0.0, eta_s=None)
        row.update(failed=0, workers=0, age_s=None)
        return row
    live = [w for w in state["workers"].values() if w["status"] in ("idle", "busy")]
    running = state["effective_status"] == "running"
    row.update(
        status=state["effective_status"],
        frames_done=state["frames_done"] + state["frames_skipped"],
        frames_per_s=state["frames_per_s"],
        # what the ETA runs at (rendered in the last RATE_WINDOW_S), shown while running
        frames_per_s_now=state.get("frames_per_s_now", 0.0) if running else 0.0,
        eta_s=state["eta_s"] if running else None,
        failed=sum(1 for f in state["failures"].values() if f["final"]),
        workers=len(live),
        waiting=sum(w["status"] == "starting" for w in state["workers"].values()) if running else 0,
        age_s=time.time() - state["started"],
        started=state["started"],
        state=state,
    )
    return row


def rates(history: list) -> list[tuple[float, float]]:
    """(time, frames rendered a second) at each progress point after the first
    (:func:`farm.state.window_rate`)."""
    return [(history[i][0], window_rate(history, i)) for i in range(1, len(history))]


def shards_with_bytes(backend: Backend) -> set[int]:
    """Shards whose renders file exists, from one listing (committed or not)."""
    path = backend.path("renders/c")
    try:
        if backend.local:
            names = os.listdir(path)
        else:
            backend.fs.invalidate_cache(path)
            names = [e.rstrip("/").rsplit("/", 1)[-1] for e in backend.fs.ls(path, detail=False)]
    except (FileNotFoundError, NotADirectoryError):
        return set()
    return {int(n) for n in names if n.isdigit()}


def shard_states(
    store: Store, committed: set[int], written: set[int], state: dict | None
) -> list[str]:
    """Per shard: ``committed``; ``failed`` (a material failed for good, or its commit);
    ``pending`` (bytes written, no commit record yet: being committed, or left by a crash);
    ``queued`` (nothing yet, the job running) or ``empty``."""
    failed = set(state.get("shards_failed", [])) if state else set()
    running = bool(state) and state.get("effective_status") == "running"
    rest = "queued" if running else "empty"
    out = []
    for s in range(store.layout.num_shards):
        if s in committed:
            out.append("committed")
        elif s in failed:
            out.append("failed")
        else:
            out.append("pending" if s in written else rest)
    return out


def workers_table(state: dict, now: float | None = None) -> list[dict]:
    now = time.time() if now is None else now
    running = state.get("effective_status") == "running"
    rows = []
    for w in state["workers"].values():
        live = w["status"] in ("idle", "busy", "starting")
        rows.append({**w, "stale": running and live and now - w["last_seen"] > STALE_S,
                     "blocklisted": w["status"] == "blocklisted"})  # fmt: skip
    return rows


def failures_table(state: dict) -> list[dict]:
    rows = []
    for m, f in sorted(state["failures"].items(), key=lambda kv: int(kv[0])):
        outcome = "final" if f["final"] else "recovered" if f.get("recovered") else "retrying"
        rows.append({"material": int(m), "attempts": f["errors"], "outcome": outcome,
                     "count": f["attempts"], "kind": f.get("kind", ""),
                     "source": f.get("source", "")})  # fmt: skip
    for shard, error in sorted(state.get("commit_failures", {}).items()):
        rows.append({"material": None, "shard": int(shard), "outcome": "final", "count": 1,
                     "kind": "", "source": "",
                     "attempts": [{"worker": "commit", "error": error}]})  # fmt: skip
    return rows


class PerSample:
    """The per-sample values the dashboard draws (sun elevation, turbidity, render seconds) of
    each committed shard, read once: a committed shard never changes, so following a running
    job reads only its new shards."""

    NAMES = ("elevation", "turbidity", "seconds")

    def __init__(self):
        self.shards: dict[str, dict[int, tuple[np.ndarray, ...]]] = {}

    def get(self, store: Store, committed: set[int]) -> dict[str, np.ndarray]:
        cache = self.shards.setdefault(store.url, {})
        new = sorted(set(committed) - set(cache))
        if new:
            g, lay = store.group, store.layout
            names = ("sun_direction", "turbidity", "render_seconds")
            if len(new) > 32:  # one read of each whole array beats many shard reads
                arrays = [g[n][:] for n in names]
                rows = {s: lay.shard_samples(s) for s in new}
                parts = {s: [a[r.start : r.stop] for a in arrays] for s, r in rows.items()}
            else:
                parts = {}
                for s in new:
                    r = lay.shard_samples(s)
                    parts[s] = [g[n][r.start : r.stop] for n in names]
            for s, (d, t, sec) in parts.items():
                elevation = np.degrees(np.arcsin(np.clip(d[:, 2], -1, 1)))
                cache[s] = (elevation, np.asarray(t, np.float64), np.asarray(sec, np.float64))
        keep = sorted(committed)
        return {name: np.concatenate([cache[s][i] for s in keep]) if keep else np.zeros(0)
                for i, name in enumerate(self.NAMES)}  # fmt: skip


def histograms(values: dict[str, np.ndarray]) -> dict:
    """Sun elevation and turbidity of the committed samples, 9 bins each."""
    out = {}
    for name, key, lo, hi in (("sun elevation (deg)", "elevation", 0, 90),
                              ("turbidity", "turbidity", 1, 10)):  # fmt: skip
        if not len(values[key]):
            out[name] = []
            continue
        counts, edges = np.histogram(values[key], bins=9, range=(lo, hi))
        pairs = zip(edges[:-1], edges[1:], counts, strict=True)
        out[name] = [(float(a), float(b), int(c)) for a, b, c in pairs]
    return out


def newest_samples(store: Store, times: dict[int, float], count: int = 8) -> list[int]:
    """Sample indices of the newest committed shards, newest first."""
    out: list[int] = []
    for shard in sorted(times, key=lambda s: -times[s]):
        out += list(store.layout.shard_samples(shard))[: count - len(out)]
        if len(out) >= count:
            break
    return out
