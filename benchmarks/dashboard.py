"""How fast the farm dashboard answers, and what it costs while it watches a running job.

    .venv/bin/python -m benchmarks.dashboard [--stores 1,100,1000] [--shards 2000]
                                             [--failures 500] [--watch-s 30]

Synthetic stores on disk (no Ray, no Blender): ``--stores`` counts of small finished jobs
(one real store, copied), and one job of ``--shards`` shards (5 frames each at 16², every
shard written and committed) with ``--failures`` failed materials and 64 workers in its
state. For each: the jobs page, the big job's page and ``/metrics``, timed from a client on
this machine (server time plus the loopback; median of 5) and in headless Chromium (the
page's load event, median of 3). Then the dashboard's CPU while a Chromium tab follows the
big job, kept "running" by a thread that rewrites its state every 2 s as a driver does: the
server process's CPU seconds over ``--watch-s`` seconds, as a share of one core.
"""

from __future__ import annotations

import argparse
import json
import shutil
import statistics
import subprocess
import sys
import threading
import time
import urllib.request
from pathlib import Path

import psutil
from tabulate import tabulate

from benchmarks.results import Table, save
from farm.state import JobState, WorkerStats, add_point
from storage.backend import Backend
from storage.schema import Layout
from storage.writer import create_store, write_shard
from tests.storage_helpers import synthetic_payload

CACHE = Path("benchmarks/.cache/dashboard")


def job_state(path: Path, layout: Layout, committed: int, failures: int, workers: int,
              status: str) -> JobState:  # fmt: skip
    st = JobState(str(path), {}, layout.num_samples, layout.num_shards, status=status)
    st.frames_done = committed * layout.shard_size
    st.shards_committed = committed
    st.started = time.time() - 3600
    for k in range(failures):
        errors = [{"worker": f"w{k % workers}", "error": "RenderError: injected", "at": 0.0}] * 3
        st.failures[str(k * 3)] = {"attempts": 3, "errors": errors, "final": True}
    st.shards_failed = sorted({k * 3 // layout.materials_per_shard for k in range(failures)})
    for w in range(workers):
        st.workers[f"w{w}"] = WorkerStats(f"w{w}", "busy", f"node{w % 8}", 1000 + w, frames=40,
                                          frame_seconds=60.0, last_seen=time.time())  # fmt: skip
    for t in range(0, 3600, 10):
        st.history = add_point(st.history, st.started + t, t // 2)
    st.save(Backend(str(path)))
    return st


def big_job(root: Path, shards: int, failures: int) -> Path:
    path = root / f"big-{shards}.zarr"
    layout = Layout(num_materials=shards, suns_per_material=5, resolution=16, shard_size=5)
    if not (path / "zarr.json").exists():
        tmp = root / f".big-{shards}.zarr"
        shutil.rmtree(tmp, ignore_errors=True)
        store = create_store(str(tmp), layout, {"samples": 4, "sources": [f"uniform:{shards}"]})
        for s in range(shards):
            write_shard(store, s, synthetic_payload(layout, s))
        tmp.rename(path)
    job_state(path, layout, shards - failures, failures, 64, "running")
    return path


def small_jobs(root: Path, count: int) -> Path:
    folder = root / f"stores-{count}"
    if not folder.exists():
        layout = Layout(num_materials=4, suns_per_material=5, resolution=16, shard_size=10)
        first = folder / "s0000.zarr"
        store = create_store(str(first), layout, {"samples": 4, "sources": ["uniform:4"]})
        for s in range(layout.num_shards):
            write_shard(store, s, synthetic_payload(layout, s))
        job_state(first, layout, layout.num_shards, 0, 2, "done")
        for k in range(1, count):
            shutil.copytree(first, folder / f"s{k:04d}.zarr")
    return folder


class Server:
    def __init__(self, *roots):
        from tests.conftest import free_port

        self.port = free_port()
        self.base = f"http://127.0.0.1:{self.port}"
        farm = str(Path(sys.executable).parent / "farm")
        self.proc = subprocess.Popen([farm, "dashboard", *map(str, roots), "--port",
                                      str(self.port)], stderr=subprocess.DEVNULL)  # fmt: skip
        for _ in range(150):
            try:
                urllib.request.urlopen(self.base + "/metrics", timeout=60).read()
                return
            except OSError:
                time.sleep(0.2)
        raise RuntimeError("the dashboard did not start")

    def close(self):
        self.proc.terminate()
        self.proc.wait(10)


def client_ms(url: str, n: int = 5) -> float:
    times = []
    for _ in range(n):
        t0 = time.perf_counter()
        urllib.request.urlopen(url, timeout=300).read()
        times.append(time.perf_counter() - t0)
    return 1e3 * statistics.median(times)


def browser_ms(page, url: str, n: int = 3) -> float:
    times = []
    for _ in range(n):
        t0 = time.perf_counter()
        page.goto(url, wait_until="load", timeout=300_000)
        times.append(time.perf_counter() - t0)
    return 1e3 * statistics.median(times)


def keep_running(path: Path, stop: threading.Event) -> None:
    """Rewrite the big job's state every 2 s, as a live driver does."""
    state_path = path / "farm" / "job.json"
    while not stop.wait(2.0):
        st = json.loads(state_path.read_text())
        st["updated"] = time.time()
        st["frames_done"] += 5
        st["history"] = add_point(st["history"], time.time(), st["frames_done"])
        tmp = state_path.with_suffix(".tmp")
        tmp.write_text(json.dumps(st))
        tmp.replace(state_path)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--stores", default="1,100,1000")
    ap.add_argument("--shards", type=int, default=2000)
    ap.add_argument("--failures", type=int, default=500)
    ap.add_argument("--watch-s", type=float, default=30.0)
    args = ap.parse_args()
    from playwright.sync_api import sync_playwright

    from tests.test_dashboard import chromium

    CACHE.mkdir(parents=True, exist_ok=True)
    print("making the synthetic stores (cached in benchmarks/.cache/dashboard)", flush=True)
    big = big_job(CACHE, args.shards, args.failures)
    counts = [int(c) for c in args.stores.split(",")]
    folders = {c: small_jobs(CACHE, c) for c in counts}
    rows = []
    with sync_playwright() as p:
        browser = p.chromium.launch(executable_path=chromium(), args=["--no-sandbox"])
        page = browser.new_page()
        for c in counts:
            s = Server(folders[c])
            try:
                rows.append((f"jobs page, {c} stores", client_ms(s.base + "/"),
                             browser_ms(page, s.base + "/")))  # fmt: skip
                rows.append((f"/metrics, {c} stores", client_ms(s.base + "/metrics"), None))
            finally:
                s.close()
        s = Server(big)
        try:
            what = f"job page, {args.shards} shards, {args.failures} failures, 64 workers"
            url = s.base + "/job/0"
            rows.append((what, client_ms(url), browser_ms(page, url)))
            rows.append(("/metrics, that job", client_ms(s.base + "/metrics"), None))
            stop = threading.Event()
            writer = threading.Thread(target=keep_running, args=(big, stop), daemon=True)
            writer.start()
            page.goto(url)
            server = psutil.Process(s.proc.pid)
            cpu0 = sum(server.cpu_times()[:2])
            time.sleep(args.watch_s)
            cpu = sum(server.cpu_times()[:2]) - cpu0
            stop.set()
        finally:
            s.close()
        browser.close()
    table = [(w, f"{a:,.0f}", "-" if b is None else f"{b:,.0f}") for w, a, b in rows]
    print(tabulate(table, ["request", "client ms (server + loopback)", "Chromium load ms"],
                   disable_numparse=True))  # fmt: skip
    print(f"dashboard CPU while a tab follows the running {args.shards}-shard job: "
          f"{100 * cpu / args.watch_s:.1f} % of one core over {args.watch_s:.0f} s")  # fmt: skip
    save("dashboard", Table(
        title="The farm dashboard (`make bench-dashboard`)",
        columns=["request", "client ms (server + loopback)", "Chromium load ms"],
        rows=[list(r) for r in table],
        notes=[f"its CPU while a tab follows the running {args.shards}-shard job: "
               f"{100 * cpu / args.watch_s:.1f} % of one core over {args.watch_s:.0f} s"],
    ))  # fmt: skip


if __name__ == "__main__":
    main()
