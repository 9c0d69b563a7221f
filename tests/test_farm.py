"""The farm on a real local Ray: end to end, resume, and the faults long Blender jobs meet."""

from __future__ import annotations

import contextlib
import http.server
import json
import os
import re
import signal
import socket
import subprocess
import sys
import threading
import time
from datetime import datetime
from pathlib import Path

import numpy as np
import psutil
import pytest

from farm.cluster import (
    address_is_loopback,
    check_reachable,
    driver_node,
    endpoint,
    not_grpc,
    token_at_hand,
)
from farm.faults import FAULTS_ENV
from farm.lease import LEASE_S, LeaseHeld, acquire, holder_alive
from farm.plan import JobConfig, layout_for, material_specs, task_for
from farm.state import effective_status
from render_jobs.specs import derive_seed
from storage.reader import Store
from storage.verify import verify
from tests.conftest import s3_env
from tests.flaky_proxy import FlakyProxy
from tests.ray_local import add_local_node, local_cluster, ray_start_head

pytestmark = pytest.mark.slow
BIN = Path(sys.executable).parent
TINY = ["--suns", "2", "--shard-size", "4", "--resolution", "32", "--samples", "2"]


def farm(*args, faults=None, wait=True, timeout=300, env=None, ray_dashboard=False):
    """The ``farm`` command, Ray's token authentication off unless ``env`` says otherwise (a
    ``None`` value removes a variable). A ``submit`` starts its embedded Ray without Ray's
    dashboard unless ``ray_dashboard``: that costs each job about 2 s, and CPU beside the
    renders, on this 2-core machine; the default is run in ``test_submit_resume_and_refusal``."""
    env = {**os.environ, "RAY_AUTH_MODE": "disabled", **(env or {})}
    env = {k: v for k, v in env.items() if v is not None}
    if faults is not None:
        env["SHADERBALL_FARM_FAULTS"] = json.dumps(faults)
    cmd = [str(BIN / "farm"), *map(str, args)]
    if args and args[0] == "submit" and not ray_dashboard and "--no-ray-dashboard" not in cmd:
        cmd.append("--no-ray-dashboard")
    if not wait:
        return subprocess.Popen(
            cmd, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True
        )
    return subprocess.run(cmd, env=env, capture_output=True, text=True, timeout=timeout)


def assert_exactly_once(path, materials: int, suns: int = 2, seed: int = 0):
    """Every sample present, once, with the seed its (material, sun) must have."""
    store = Store(str(path))
    assert store.committed_shards() == list(range(store.layout.num_shards))
    seeds = store.group["seed"][:]
    want = [derive_seed(seed, m, k) for m in range(materials) for k in range(suns)]
    np.testing.assert_array_equal(seeds, want)
    report = verify(store)  # in process: `shards verify` itself is tested in test_storage.py
    assert report.ok, (report.store_problems, report.problems)


def wait_until(done, timeout: float, failure: str) -> None:
    """Poll ``done()`` every 0.2 s until it is true; fail with ``failure`` after ``timeout``."""
    deadline = time.time() + timeout
    while not done():
        if time.time() > deadline:
            raise AssertionError(f"{failure} (after {timeout:.0f} s)")
        time.sleep(0.2)


def wait_for_commits(out: Path, count: int, timeout: float = 120) -> None:
    """Poll until ``count`` shards of the store at ``out`` are committed; fail after ``timeout``."""
    commits = out / "commits"
    wait_until(
        lambda: commits.exists() and len(list(commits.glob("*.json"))) >= count,
        timeout,
        f"fewer than {count} shards of {out} committed",
    )


def job(path) -> dict:
    return json.loads((Path(path) / "farm" / "job.json").read_text())


def test_plan_is_deterministic():
    cfg = JobConfig(sources=("uniform:3", "procedural:2"), out="x", suns=3, seed=7)
    a = [task_for(cfg, i, s) for i, s in enumerate(material_specs(cfg))]
    b = [task_for(cfg, i, s) for i, s in enumerate(material_specs(cfg))]
    assert a == b and len(a) == 5 and all(len(t.suns) == 3 for t in a)
    assert len({t.seeds for t in a}) == 5
    other = JobConfig(sources=("uniform:3", "procedural:2"), out="x", suns=3, seed=8)
    assert task_for(other, 0, material_specs(other)[0]) != a[0]


def test_submit_resume_and_refusal(tmp_path):
    out = tmp_path / "set.zarr"
    r = farm(
        "submit", "-m", "uniform:3", "-m", "procedural:2", *TINY, "--recycle-after", "2", "-o", out,
        env={"RAY_AUTH_MODE": None},  # as people run it: Ray's default, token authentication
        ray_dashboard=True,  # and the farm's: the embedded Ray with its dashboard
    )  # fmt: skip
    assert r.returncode == 0, r.stderr
    assert "10 rendered" in r.stdout and "ray dashboard: http" in r.stdout
    assert r.stdout.startswith("starting Ray on this machine\n")  # before Ray's seconds
    assert "Started a local Ray instance" not in r.stderr  # Ray's own line: said above
    assert "Token authentication" not in r.stderr  # the farm says token, so Ray need not warn
    assert f"shards info {out}" in r.stdout
    assert_exactly_once(out, 5)
    state = job(out)
    assert state["status"] == "done" and state["frames_done"] == 10
    assert sum(w["frames"] for w in state["workers"].values()) == 10
    assert sum(w["recycled"] for w in state["workers"].values()) >= 2  # --recycle-after 2
    assert {w["nice"] for w in state["workers"].values()} == {0}  # not Ray's default 15
    status = farm("status", out)
    assert status.returncode == 0 and "10/10" in status.stdout and "w0" in status.stdout
    again = farm("submit", "-m", "uniform:3", "-m", "procedural:2", *TINY, "-o", out)
    assert again.returncode == 0 and "0 rendered, 10 already there" in again.stdout
    other = farm("submit", "-m", "uniform:3", "-m", "procedural:2", *TINY[:-1], "8", "-o", out)
    assert other.returncode == 1
    assert other.stderr.strip().splitlines()[-1].startswith("Error: ")
    assert "settings.samples=2, not 8" in other.stderr
    rounded = farm("submit", "-m", "uniform:3", "-m", "procedural:2", *TINY, "--render-bits", "6",
                   "-o", out)  # fmt: skip
    assert rounded.returncode == 1 and "settings.render_bits=None, not 6" in rounded.stderr


def test_a_store_keeps_a_render_bits_setting_only_where_bits_are_dropped():
    """A store made before the setting existed is the same dataset as one made with all 10."""
    sources = ("uniform:2",)
    assert "render_bits" not in JobConfig(sources=sources, out="x").dataset_settings()
    kept = JobConfig(sources=sources, out="x", render_bits=6).dataset_settings()
    assert kept["render_bits"] == 6
    for bad in (0, 11):
        with pytest.raises(ValueError, match=r"--render-bits must be in \[1, 10\], not"):
            JobConfig(sources=sources, out="x", render_bits=bad)


@pytest.mark.parametrize("suns,want", [(1, 5), (3, 15), (5, 25), (7, 35)])
def test_default_shard_size_follows_the_suns(suns, want):
    cfg = JobConfig(sources=("uniform:2",), out="x", suns=suns)
    assert cfg.shard_size == want and layout_for(cfg, 2).materials_per_shard == 5
    assert JobConfig(sources=("uniform:2",), out="x", suns=3, shard_size=6).shard_size == 6


def test_suns_without_a_shard_size_pass_the_shard_check(tmp_path):
    """``--suns 3`` alone is valid: the run gets as far as the (missing) material folder."""
    r = farm("submit", "-m", f"svbrdf:{tmp_path / 'none'}", "--suns", "3", "-o", tmp_path / "s")
    assert r.returncode == 1 and "multiple of --suns" not in r.stderr
    assert "none" in r.stderr and "Traceback" not in r.stderr


def test_a_lease_binds_while_renewed_and_its_driver_lives():
    me = {"host": "here", "pid": os.getpid(), "started": psutil.Process().create_time()}
    assert holder_alive({**me, "renewed": 100.0}, now=110.0, here="here")
    assert not holder_alive({**me, "renewed": 100.0}, now=100.0 + LEASE_S + 1, here="here")
    gone = subprocess.Popen([sys.executable, "-c", "pass"])
    gone.wait()
    dead = {"host": "here", "pid": gone.pid, "started": 0.0, "renewed": 100.0}
    assert not holder_alive(dead, now=101.0, here="here")  # a killed driver frees it at once
    assert holder_alive({**dead, "host": "elsewhere"}, now=101.0, here="here")  # can't tell


def test_of_drivers_racing_for_a_local_store_one_takes_it_under_the_lock(tmp_path, monkeypatch):
    """Eight at once: one lease, seven refusals naming its holder; on a local store the lock
    decides, with no settle wait (``time.sleep`` in the lease module would fail)."""
    import threading

    from storage.backend import Backend

    monkeypatch.setattr("farm.lease.time.sleep", lambda s: pytest.fail("settled"))
    url, go, got = str(tmp_path / "set.zarr"), threading.Barrier(8), []

    def take() -> None:
        go.wait()
        try:
            got.append(acquire(url, Backend(url)))
        except LeaseHeld as exc:
            got.append(exc)

    threads = [threading.Thread(target=take) for _ in range(8)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    leases = [g for g in got if not isinstance(g, LeaseHeld)]
    assert len(got) == 8 and len(leases) == 1
    assert all("another farm submit is running" in str(g) for g in got if g is not leases[0])
    leases[0].release()
    acquire(url, Backend(url)).release()  # free again


def test_a_running_state_is_lost_once_its_drivers_lease_is_dead():
    host = socket.gethostname()
    me = {"host": host, "pid": os.getpid(), "started": psutil.Process().create_time()}
    running = {"status": "running", "updated": 100.0}
    assert effective_status(running, {**me, "renewed": 100.0}, 105.0) == "running"
    assert effective_status(running, {**me, "renewed": 100.0}, 100.0 + LEASE_S + 1) == "lost"
    gone = subprocess.Popen([sys.executable, "-c", "pass"])
    gone.wait()
    dead = {"host": host, "pid": gone.pid, "started": 0.0, "renewed": 100.0}
    assert effective_status(running, dead, 101.0) == "lost"  # killed here: lost at once
    # no lease record beside the state: the state's driver and age decide, by the same rule
    assert effective_status(running, None, 100.0 + LEASE_S - 1) == "running"
    assert effective_status(running, None, 100.0 + LEASE_S + 1) == "lost"
    mine = {**running, "driver": f"{host}:{os.getpid()}"}
    assert effective_status(mine, None, 100.0 + LEASE_S - 1) == "running"
    assert effective_status({**running, "driver": f"{host}:{gone.pid}"}, None, 101.0) == "lost"
    assert effective_status({"status": "done", "updated": 0.0}, dead, 1e9) == "done"


def test_status_names_the_ray_dashboard_only_while_the_job_runs():
    from farm.status import format_status

    st = {"status": "running", "driver": "vm:1", "updated": time.time(), "store": "s.zarr",
          "frames_done": 4, "frames_skipped": 0, "frames_total": 8, "frames_per_s": 1.0,
          "eta_s": 4.0, "shards_committed": 1, "shards_total": 2, "shards_failed": [],
          "dashboard": "http://127.0.0.1:8265", "failures": {}, "workers": {}}  # fmt: skip
    assert "ray       http://127.0.0.1:8265" in format_status(st)
    assert "1.00 frames/s, ETA 4 s" in format_status(st)  # a state without the recent rate
    now = format_status({**st, "frames_per_s_now": 1.5})
    assert "1.00 frames/s (1.50 rendered in the last 30 s), ETA 4 s" in now
    for status in ("done", "lost"):
        assert "8265" not in format_status({**st, "effective_status": status})
    w = {"worker": "w0", "status": "busy", "frames": 4, "mean_frame_s": 0.5, "failures": 0,
         "recycled": 1, "recalled": 2, "last_seen": time.time()}  # fmt: skip
    table = format_status({**st, "workers": {"w0": w}}).splitlines()[-3:]
    assert table[0].split()[5:7] == ["recycled", "recalled"]
    assert table[2].split()[:7] == ["w0", "busy", "4", "0.50", "0", "1", "2"]
    old = {k: v for k, v in w.items() if k != "recalled"}  # a state written before the column
    assert format_status({**st, "workers": {"w0": old}}).splitlines()[-1].split()[6] == "0"


def test_status_lists_each_failed_material_and_commit_between_the_job_and_its_workers():
    from farm.status import format_status

    st = {"status": "running", "driver": "vm:1", "updated": time.time(), "store": "s.zarr",
          "frames_done": 4, "frames_skipped": 0, "frames_total": 8, "frames_per_s": 1.0,
          "eta_s": 4.0, "shards_committed": 1, "shards_total": 2, "shards_failed": [1],
          "failures": {}, "workers": {}}  # fmt: skip
    assert "failures" not in format_status(st).splitlines()
    err = lambda e: {"worker": "w1", "error": e}  # noqa: E731
    st["failures"] = {
        "10": {"attempts": 3, "final": True, "errors": [err("a"), err("Blender crashed")]},
        "2": {"attempts": 2, "final": False, "recovered": True, "errors": [err("timeout")]},
        "7": {"attempts": 1, "final": False, "errors": []},
    }
    st["commit_failures"] = {"1": "store unreachable"}
    lines = format_status(st).splitlines()
    at = lines.index("failures")
    assert lines[at - 1] == "shards    1/2 committed, failed: 1 (shard 1)"
    many = format_status({**st, "shards_failed": list(range(3, 23))}).splitlines()[3]
    assert many.endswith("failed: 20 (shards 3, 4, 5, 6, 7, 8, 9, 10, ...)")
    assert [ln.split()[:4] for ln in lines[at + 1 : at + 5]] == [
        ["material", "2", "recovered", "attempts"],
        ["material", "7", "retrying", "attempts"],
        ["material", "10", "FAILED", "attempts"],
        ["shard", "1", "FAILED", "commit:"],
    ]
    assert lines[at + 3].endswith("attempts 3  last on w1: Blender crashed")
    assert lines[at + 2].endswith("last on -: -") and lines[at + 5].startswith("workers   0")


def test_status_counts_a_cluster_jobs_workers_and_lists_the_first_twenty():
    from farm.status import format_status

    st = {"status": "running", "driver": "vm:1", "updated": time.time(), "store": "s.zarr",
          "frames_done": 4, "frames_skipped": 0, "frames_total": 8, "frames_per_s": 1.0,
          "eta_s": 4.0, "shards_committed": 1, "shards_total": 2, "shards_failed": [],
          "failures": {}, "workers": {}}  # fmt: skip
    assert "workers   0\n" in format_status(st)
    statuses = ["busy"] * 20 + ["idle"] * 5 + ["starting"] * 4 + ["dead"]
    st["workers"] = {f"w{i}": {"worker": f"w{i}", "status": s, "frames": 0, "mean_frame_s": 0.0,
                               "failures": 0, "recycled": 0, "last_seen": time.time()}
                     for i, s in enumerate(statuses)}  # fmt: skip
    lines = format_status(st).splitlines()
    assert "workers   30: 20 busy, 5 idle, 4 starting, 1 dead" in lines
    assert [ln.split()[0] for ln in lines[-21:-1]] == [f"w{i}" for i in range(20)]
    assert lines[-1] == "... 10 more (farm status --all-workers)"
    every = format_status(st, None).splitlines()
    assert every[-1].split()[:2] == ["w29", "dead"] and "more" not in every[-2]


def test_a_job_no_worker_can_be_placed_for_stops_failed_and_says_why(tmp_path):
    """A GPU worker on a machine with no GPU: Ray never places it. After --placement-timeout
    the job stops in one line, and its state, ``farm status`` and the dashboard say why."""
    out = tmp_path / "set.zarr"
    r = farm("submit", "-m", "uniform:2", *TINY, "--gpus-per-worker", "1",
             "--placement-timeout", "3", "-o", out)  # fmt: skip
    why = "no live worker for 3 s: Ray could not place a worker needing 1 CPU(s) and 1 GPU(s)"
    assert r.returncode == 1 and r.stderr.strip().splitlines()[-1] == f"Error: {why}", r.stderr
    st = job(out)
    assert st["status"] == "failed" and st["stop_error"] == why
    assert [w["status"] for w in st["workers"].values()] == ["unplaced"]
    assert f"stopped   {why}" in farm("status", out).stdout
    from farm.status import format_status

    uv = format_status({**st, "screen_uv_error": "RenderError: boom"})
    assert "screen UV layout not made: RenderError: boom (farm screen-uv makes it)" in uv


def test_a_worker_waiting_for_room_is_given_up_when_the_queue_runs_dry(tmp_path, monkeypatch):
    """``--workers 2`` on a one-CPU cluster: the second worker waits for room. Once the first
    holds every task left (the last one slowed 8 s), the waiting one is given up (on an
    autoscaling cluster it is a node asked for) and ends ``unplaced``; the job renders
    everything and takes no 15 s waiting for it to close."""
    monkeypatch.setenv("RAY_AUTH_MODE", "disabled")
    # the last material is slow: the queue stays empty for longer than a resize period (the
    # faults reach the workers through their node)
    cluster = local_cluster(1, {FAULTS_ENV: json.dumps({"slow_materials": {"2": 8}})})
    out = tmp_path / "set.zarr"
    try:
        cluster.wait_for_nodes()
        r = farm("submit", "-m", "uniform:3", *TINY, "--workers", "2",
                 "--address", cluster.address, "-o", out)  # fmt: skip
    finally:
        cluster.shutdown()
    assert r.returncode == 0, r.stderr[-3000:]
    assert "2 workers, room for 1 now: the others wait for room" in r.stdout
    assert "0 tasks queued: giving up 1 of the workers waiting for room" in r.stdout + r.stderr
    assert_exactly_once(out, 3)
    # Ray may place either of the two workers first
    assert sorted(w["status"] for w in job(out)["workers"].values()) == ["stopped", "unplaced"]


def test_a_retry_waits_for_a_worker_ray_cannot_place_no_longer_than_retry_wait(
    tmp_path, monkeypatch
):
    """``--workers 2`` on a one-CPU cluster: the second worker never finds room. The first
    fails material 0's first try; the retry waits ``--retry-wait 3`` seconds for the worker
    that has not failed it, then runs on the one that has, and the job ends whole (it would
    wait for as long as the second worker waits for room: here, for ever)."""
    monkeypatch.setenv("RAY_AUTH_MODE", "disabled")
    trace = tmp_path / "trace"
    faults = {"flaky_materials": [0], "flaky_marker": str(tmp_path / "tried"),
              "trace": str(trace)}  # fmt: skip
    cluster = local_cluster(1, {FAULTS_ENV: json.dumps(faults)})
    out = tmp_path / "set.zarr"
    try:
        cluster.wait_for_nodes()
        r = farm("submit", "-m", "uniform:2", *TINY, "--workers", "2", "--retry-wait", "3",
                 "--address", cluster.address, "-o", out, timeout=240)  # fmt: skip
    finally:
        cluster.shutdown()
    assert r.returncode == 0, r.stderr[-3000:]
    st = job(out)
    failure = st["failures"]["0"]
    assert failure["recovered"] and failure["attempts"] == 1, st["failures"]
    tries = [line.split()[0] for line in trace.read_text().splitlines() if line.endswith(" 0")]
    assert len(tries) == 2 and tries[0] == tries[1] == failure["errors"][0]["worker"]
    assert_exactly_once(out, 2)
    assert sorted(w["status"] for w in st["workers"].values()) == ["stopped", "unplaced"]


def test_an_idle_worker_is_released_at_the_tail_and_a_retry_runs_on_a_fresh_one(tmp_path):
    """``--workers 2``, 3 materials, the last slowed 10 s and failing its first try: while it
    renders, the worker left with nothing is released (its node could go). The retry does not
    go back to the worker that failed it: a fresh one is started for it (or, had the release
    come only later, the other worker takes it), the one that failed is released in turn, and
    the job ends with every sample once."""
    out, trace = tmp_path / "set.zarr", tmp_path / "trace"
    faults = {"slow_materials": {"2": 10}, "flaky_materials": [2],
              "flaky_marker": str(tmp_path / "tried"), "trace": str(trace)}  # fmt: skip
    r = farm("submit", "-m", "uniform:3", *TINY, "--workers", "2",
             "-o", out, faults=faults)  # fmt: skip
    assert r.returncode == 0, r.stderr[-3000:]
    assert "0 tasks queued, 1 running: releasing 1 idle worker (w" in r.stdout + r.stderr
    st = job(out)
    failure = st["failures"]["2"]
    assert failure["recovered"] and failure["attempts"] == 1, st["failures"]
    assert "retried   1 failed attempt(s), every material rendered on a retry" in r.stdout
    assert "Unhandled error" not in r.stderr  # the failed try's results were read
    tries = [line.split()[0] for line in trace.read_text().splitlines() if line.endswith(" 2")]
    assert len(tries) == 2 and tries[0] != tries[1], trace.read_text()  # retried elsewhere
    assert tries[0] == failure["errors"][0]["worker"]
    assert_exactly_once(out, 3)
    statuses = {w: s["status"] for w, s in st["workers"].items()}
    assert statuses[tries[0]] == "released" and statuses[tries[1]] == "stopped", statuses
    if "w2" in statuses:  # the fresh one: started for the retry, after the tail release
        assert "1 tasks queued: starting 1 worker again (--workers 2)" in r.stdout + r.stderr
        assert sorted(statuses.values()) == ["released", "released", "stopped"], statuses


READ_ERRORS = """
import gc, sys, time
import ray
from farm.pool import read_errors

# its own Ray ("local"), not a cluster another test started with `ray start`
ray.init(address="local", num_cpus=1, include_dashboard=False, log_to_driver=False,
         _node_ip_address="127.0.0.1")


@ray.remote
class Late:
    def fail(self, tag):
        time.sleep(1)
        raise ValueError(tag)

    def succeed(self):
        return {"ok": True}, b"arrays"


late = Late.remote()
control = late.fail.options(num_returns=2).remote("left-unread")
ray.wait([control[0]], fetch_local=False)
with __import__("contextlib").suppress(Exception):
    ray.get(control[0])  # the report read, the arrays' copy of the error left
failed = late.fail.options(num_returns=2).remote("read")
print("failed", read_errors(failed), flush=True)  # neither has come yet: both waited for
print("fine", read_errors(late.succeed.options(num_returns=2).remote()), flush=True)
del control, failed
gc.collect()
time.sleep(3)
"""


def test_every_result_of_a_failed_task_is_read_even_before_it_comes():
    """A failed task's report and arrays reach the driver one after another; reading the
    errors waits for each, so no copy of the error is left for Ray to print as unhandled.
    The control, whose arrays are left unread, shows that Ray prints what was left."""
    env = {**os.environ, "RAY_AUTH_MODE": "disabled"}
    r = subprocess.run([sys.executable, "-c", READ_ERRORS], env=env, capture_output=True,
                       text=True, timeout=120)  # fmt: skip
    assert r.returncode == 0, r.stderr[-3000:]
    assert "failed 2\nfine 0\n" in r.stdout
    assert "ValueError: left-unread" in r.stderr  # the control: Ray prints an unread error
    assert "ValueError: read" not in r.stderr


def test_two_submits_at_once_one_renders_the_other_refuses(tmp_path):
    out = tmp_path / "set.zarr"
    args = ["submit", "-m", "uniform:4", *TINY, "--workers", "1", "-o", out]
    procs = [farm(*args, wait=False) for _ in range(2)]
    try:
        results = [(p.wait(240), *p.communicate()) for p in procs]
    finally:
        for p in procs:
            p.kill()
    codes = sorted(rc for rc, _, _ in results)
    assert codes == [0, 1], results
    _, _, err = next(r for r in results if r[0] == 1)
    assert err.strip().splitlines()[-1].startswith("Error: ")
    assert "another farm submit is running on this store (driver " in err
    assert "Traceback" not in err
    assert_exactly_once(out, 4)
    assert not (out / "farm" / "lease.json").exists()  # released at the end
    assert farm("submit", *args[1:]).returncode == 0  # and the store is free again


def test_ray_addresses_name_what_must_answer():
    assert endpoint("10.0.0.5:6379") == ("10.0.0.5", 6379)
    assert endpoint("ray://head") == ("head", 10001)
    assert endpoint("ray://head.ns.svc:10002") == ("head.ns.svc", 10002)
    assert endpoint("[::1]:6379") == ("::1", 6379)
    assert endpoint("auto") is None and endpoint("local") is None
    assert endpoint("http://head:8265") is None  # not a form ray.init takes: Ray says so
    loopback = ["127.0.0.1:6379", "localhost:6379", "[::1]:6379", "ray://127.0.0.2", None]
    assert all(address_is_loopback(a) for a in loopback)
    assert not any(
        address_is_loopback(a) for a in ["10.0.0.5:6379", "ray://head", "auto", "[::2]:1"]
    )


def answering(reply: bytes | None, hold: threading.Event) -> tuple[str, int]:
    """A one-connection TCP server on 127.0.0.1 that reads a greeting and sends ``reply``
    and closes (``None``: says nothing until ``hold`` is set)."""
    server = socket.create_server(("127.0.0.1", 0))

    def serve():
        conn, _ = server.accept()
        with conn, server:
            conn.recv(64)
            if reply is None:
                hold.wait(10)
            else:
                conn.sendall(reply)

    threading.Thread(target=serve, daemon=True).start()
    return server.getsockname()[:2]


def test_only_a_server_that_surely_is_not_grpc_is_named_so():
    hold = threading.Event()
    try:
        assert "does not speak gRPC" in not_grpc(answering(b"-ERR unknown command\r\n", hold))
        assert "closed the connection" in not_grpc(answering(b"", hold))
        assert "a web server" in not_grpc(answering(b"HTTP/1.1 400 Bad Request\r\n\r\n", hold))
        # an HTTP/2 server's first frame: a SETTINGS frame header (a GCS's is not empty)
        assert not_grpc(answering(bytes([0, 0, 6, 4, 0, 0, 0, 0, 0]), hold)) is None
        assert not_grpc(answering(None, hold), timeout_s=0.5) is None  # silent: Ray decides
        assert not_grpc(("127.0.0.1", closed_port())) is None  # check_reachable's case
    finally:
        hold.set()


def test_a_driver_joins_a_loopback_cluster_through_a_node_of_its_own_machine():
    here = {"127.0.0.1", "::1", "192.0.2.2"}
    assert driver_node("x", ["127.0.0.1"], here) == "127.0.0.1"  # --node-ip-address 127.0.0.1
    assert driver_node("x", ["192.0.2.2"], here) == "192.0.2.2"  # ray start --head's default
    assert driver_node("x", ["10.0.0.9", "192.0.2.2", "127.0.0.1"], here) == "127.0.0.1"
    with pytest.raises(
        ValueError,
        match=r"^--address 127.0.0.1:6379: no node of that Ray "
        r"cluster runs on this machine \(its nodes: 10.0.0.8, 10.0.0.9\); ",
    ):
        driver_node("--address 127.0.0.1:6379", ["10.0.0.9", "10.0.0.8"], here)
    with pytest.raises(ValueError, match=r"\(its nodes: none alive\)"):
        driver_node("x", [], here)


def test_a_token_is_at_hand_where_ray_would_find_one(tmp_path):
    assert not token_at_hand({}, home=tmp_path)
    (tmp_path / ".ray").mkdir()
    (tmp_path / ".ray" / "auth_token").write_text("\n")
    assert not token_at_hand({}, home=tmp_path)  # empty
    (tmp_path / ".ray" / "auth_token").write_text("t0k\n")
    assert token_at_hand({}, home=tmp_path)
    assert token_at_hand({"RAY_AUTH_TOKEN": "t"}, home=tmp_path / "none")
    assert not token_at_hand({"RAY_AUTH_TOKEN_PATH": str(tmp_path / "gone")}, home=tmp_path)
    assert token_at_hand({"RAY_AUTH_TOKEN_PATH": str(tmp_path / ".ray" / "auth_token")})


def test_a_cluster_started_by_ray_start_is_joined_at_127_0_0_1_with_its_token(tmp_path):
    """``ray start --head`` as docs/farm.md says (Ray's defaults: the machine's outward
    address, token authentication), joined as ``--address 127.0.0.1:PORT`` with nothing
    set: the driver sends the token at hand and joins the cluster's node. A wrong token, or
    none, is one line before anything is written."""
    as_people = {"RAY_AUTH_MODE": None, "RAY_ADDRESS": None}
    with ray_start_head(2) as address:
        out = tmp_path / "joined.zarr"
        r = farm("submit", "-m", "uniform:1", *TINY, "--workers", "1", "--address", address,
                 "-o", out, env=as_people)  # fmt: skip
        assert r.returncode == 0, r.stderr[-2000:]
        assert f"joining the Ray cluster at {address}\n" in r.stdout
        assert "Connecting to existing Ray cluster" not in r.stderr  # Ray's own line
        assert_exactly_once(out, 1)
        for env, said in [
            ({"RAY_AUTH_TOKEN": "wrong"}, "token; give it the cluster's token"),
            ({"RAY_AUTH_MODE": "disabled"}, "request without a token; give it"),
        ]:
            bad = tmp_path / "refused.zarr"
            r = farm("submit", "-m", "uniform:1", *TINY, "--address", address, "-o", bad,
                     env={**as_people, **env})  # fmt: skip
            assert r.returncode == 1 and len(r.stderr.strip().splitlines()) == 1, r.stderr
            assert f"Error: --address {address}: the Ray cluster refused this driver's " in r.stderr
            assert said in r.stderr and "~/.ray/auth_token" in r.stderr, r.stderr
            assert not bad.exists()


def closed_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def test_a_ray_address_is_reachable_or_named_after_the_timeout(monkeypatch):
    with socket.create_server(("127.0.0.1", 0)) as server:
        check_reachable(f"127.0.0.1:{server.getsockname()[1]}", timeout_s=1)
    port = closed_port()
    t0 = time.monotonic()
    with pytest.raises(ConnectionError, match=rf"^--address 127.0.0.1:{port}: nothing answers"):
        check_reachable(f"127.0.0.1:{port}", timeout_s=1)
    assert 1 <= time.monotonic() - t0 < 10  # tried again until the timeout, then gave up
    monkeypatch.setenv("RAY_ADDRESS", f"ray://127.0.0.1:{port}")
    with pytest.raises(ConnectionError, match=r"^RAY_ADDRESS ray://127.0.0.1:\d+: nothing"):
        check_reachable(None, timeout_s=0.5)


def test_a_ray_cluster_out_of_reach_stops_the_job_in_one_line_before_any_write(tmp_path):
    address = f"127.0.0.1:{closed_port()}"
    r = farm("submit", "-m", "uniform:1", *TINY, "--address", address, "-o", tmp_path / "x.zarr")
    assert r.returncode == 1 and len(r.stderr.strip().splitlines()) == 1, r.stderr
    assert f"--address {address}: nothing answers there (Connection refused" in r.stderr
    assert not (tmp_path / "x.zarr").exists()


def test_a_web_server_at_the_ray_address_is_refused_at_once(tmp_path):
    """Ray's client waits some 40 s for a GCS at an address where a web server answers (the
    dashboard's port given for the GCS's); the job says so in one line at once."""
    web = http.server.ThreadingHTTPServer(("127.0.0.1", 0), http.server.SimpleHTTPRequestHandler)
    threading.Thread(target=web.serve_forever, daemon=True).start()
    try:
        for address, wanted in [
            (f"127.0.0.1:{web.server_port}", "the GCS (HEAD:6379"),
            (f"ray://127.0.0.1:{web.server_port}", "Ray's client server (ray://HEAD:10001)"),
        ]:
            start = time.monotonic()
            r = farm("submit", "-m", "uniform:1", *TINY, "--address", address,
                     "-o", tmp_path / "x.zarr")  # fmt: skip
            assert r.returncode == 1 and len(r.stderr.strip().splitlines()) == 1, r.stderr
            assert f"--address {address}: a web server answers there, not Ray" in r.stderr
            assert f"give the address of {wanted}" in r.stderr
            assert time.monotonic() - start < 30  # not Ray's own wait
            assert not (tmp_path / "x.zarr").exists()
    finally:
        web.shutdown()


def test_bad_material_stops_before_anything_starts(tmp_path):
    (tmp_path / "m").mkdir()
    (tmp_path / "m" / "broken.png").write_bytes(b"nope")
    r = farm(
        "submit",
        "-m",
        "uniform:2",
        "-m",
        f"svbrdf:{tmp_path / 'm'}",
        *TINY,
        "-o",
        tmp_path / "set.zarr",
    )
    assert r.returncode == 1 and "broken.png: not a readable image" in r.stderr
    assert "Traceback" not in r.stderr and not (tmp_path / "set.zarr").exists()
    r = farm(
        "submit", "-m", "uniform:2", "--suns", "3", "--shard-size", "4", "-o", tmp_path / "x.zarr"
    )
    assert r.returncode == 1 and "multiple of --suns" in r.stderr
    r = farm("submit", "-m", "uniform:2", "--resolution", "100", "-o", tmp_path / "y.zarr")
    assert r.returncode == 1 and len(r.stderr.strip().splitlines()) == 1, r.stderr
    assert "--resolution 100 is not a multiple of 16" in r.stderr and "try 96 or 112" in r.stderr
    assert not (tmp_path / "y.zarr").exists()


def descendants(root: int, name: str) -> list[psutil.Process]:
    """The processes under ``root`` (a driver, or this test's own Ray cluster) whose command
    line holds ``name``: a test kills only its own job's, whatever else runs beside it."""
    out = []
    for p in psutil.Process(root).children(recursive=True):
        with contextlib.suppress(psutil.NoSuchProcess):  # ended meanwhile
            if name in " ".join(p.cmdline()):
                out.append(p)
    return out


def _blender_of(actor: psutil.Process) -> list[psutil.Process]:
    """The render actor's Blender child (the spawned ``RenderProcess``)."""
    return [c for c in actor.children() if "spawn_main" in " ".join(c.cmdline())]


def _dead(p: psutil.Process) -> bool:
    """Ended, or a zombie its parent has not reaped yet (a held actor reaps it later)."""
    try:
        return p.status() == psutil.STATUS_ZOMBIE
    except psutil.NoSuchProcess:
        return True


def test_killed_blender_and_killed_worker_lose_nothing(tmp_path):
    """Both workers hold a task (``hold_while``) when one's Blender and the other whole are
    killed: the first renders on with a fresh Blender, the second's task fails and is
    rendered again, and the store holds every frame once."""
    out, hold, trace = tmp_path / "set.zarr", tmp_path / "hold", tmp_path / "trace"
    hold.touch()
    faults = {"hold_while": str(hold), "trace": str(trace)}
    args = ["submit", "-m", "uniform:8", *TINY, "--workers", "2", "-o", out]
    proc = farm(*args, faults=faults, wait=False)
    watch = None
    try:
        wait_until(lambda: len(traced_workers(trace)) == 2, 120, "two never held tasks")
        kept, killed = descendants(proc.pid, "ray::RenderWorker")
        blender = _blender_of(kept)
        assert len(blender) == 1
        # the render actor's Blender ran nothing of the actor's main script (Ray's worker)
        assert not [m for m in blender[0].memory_maps() if "_raylet" in m.path]
        blender[0].send_signal(signal.SIGKILL)  # Blender dies inside a task
        wait_until(lambda: _dead(blender[0]), 30, "the killed Blender lives")
        killed.send_signal(signal.SIGKILL)  # and then a whole Ray worker
        hold.unlink()
        watch = farm("status", out, "--watch", wait=False)  # follows the job to its end
        stdout, stderr = proc.communicate(timeout=240)
        watched, _ = watch.communicate(timeout=30)
    finally:
        proc.kill()
        if watch is not None:
            watch.kill()
    assert proc.returncode == 0, stderr
    refreshes = re.split(r"(?m)^frames {4}", watched)  # the line after each refresh's job line
    assert watch.returncode == 0 and len(refreshes) >= 3
    assert "job       done" in refreshes[-2]  # the last refresh
    assert_exactly_once(out, 8)
    workers = {w["pid"]: w for w in job(out)["workers"].values()}
    assert workers[killed.pid]["status"] == "dead"
    assert workers[kept.pid]["status"] != "dead" and workers[kept.pid]["materials"] >= 1
    failures = job(out)["failures"].values()
    assert [f for f in failures if f.get("recovered") and "worker died" in f["errors"][-1]["error"]]
    assert not any(f["final"] for f in failures)


def test_blender_is_recycled_above_the_rss_bound(tmp_path):
    out = tmp_path / "set.zarr"
    r = farm("submit", "-m", "uniform:3", *TINY, "--rss-limit-mb", "64", "-o", out)
    assert r.returncode == 0, r.stderr
    assert_exactly_once(out, 3)
    # a kept-loaded Blender holds well over 64 MB: it is restarted after every material
    assert sum(w["recycled"] for w in job(out)["workers"].values()) == 3


def test_failing_material_is_retried_elsewhere_then_recorded(tmp_path):
    """A material that fails every time is retried on the other worker, then recorded.
    Material 0 is held until the first failure is recorded, so that the other worker is busy
    then: one that had rendered everything else would be released at the job's tail (nothing
    left to take), and the retry would run on a fresh worker started for it instead."""
    out, hold = tmp_path / "set.zarr", tmp_path / "hold"
    hold.touch()
    faults = {"fail_materials": [1], "hold_materials": {"while": str(hold), "materials": [0]}}
    proc = farm("submit", "-m", "uniform:4", *TINY, "--workers", "2", "-o", out,
                faults=faults, wait=False)  # fmt: skip
    output, state = Output(proc), out / "farm" / "job.json"  # its pipes read meanwhile

    def failed() -> bool:
        return state.exists() and "1" in job(out)["failures"]

    try:
        wait_until(failed, 180, "material 1's first failure was never recorded")
        hold.unlink()
        r = subprocess.CompletedProcess(proc.args, *output.wait(300))
    finally:
        proc.kill()
    assert r.returncode == 1
    assert "material 1: RenderError: injected fault" in r.stderr
    assert "shards [0] are not committed" in r.stderr
    store = Store(str(out))
    assert store.committed_shards() == [1]  # the rest of the job completed
    f = job(out)["failures"]["1"]
    assert f["final"] and f["attempts"] == 3
    assert f["kind"] == "uniform" and f["source"].startswith("uniform:seed=")
    assert {e["worker"] for e in f["errors"]} >= {"w0", "w1"}  # retried on another worker
    assert job(out)["status"] == "failed"


def test_an_idle_worker_takes_back_a_task_waiting_behind_a_slow_one(tmp_path):
    """Three materials on two workers, material 0 taking 30 s and the others 12: whichever way
    they are dealt, one worker runs material 0 with another queued behind it, and the other,
    done with nothing queued, takes that one (recalled) and renders it. The job ends with
    material 0, in about 32 s of rendering, not 44, and the busy worker skips the recalled
    task (revoked): every material starts once. Every sample once."""
    out, trace = tmp_path / "set.zarr", tmp_path / "trace"
    faults = {"slow_materials": {"0": 30, "1": 12, "2": 12}, "trace": str(trace)}
    r = farm("submit", "-m", "uniform:3", *TINY, "--workers", "2", "-o", out, faults=faults)
    assert r.returncode == 0, r.stderr[-3000:]
    assert_exactly_once(out, 3)
    workers = sorted((w["materials"], w["recalled"]) for w in job(out)["workers"].values())
    assert workers == [(1, 1), (2, 0)]  # the slow one gave its waiting task to the other
    started = sorted(int(line.split()[1]) for line in trace.read_text().splitlines())
    assert started == [0, 1, 2], trace.read_text()  # no run of the recalled task at the slow one
    wall, startup = map(
        float, re.search(r"time +([\d.]+) s .*start-up ([\d.]+) s", r.stdout).groups()
    )
    assert wall - startup < 36, r.stdout  # 30 s and the commits; 42 s behind material 0


def test_bad_worker_is_blocklisted_and_replaced(tmp_path):
    out, trace = tmp_path / "set.zarr", tmp_path / "trace"
    # w1 renders nothing until the replacement w2 has a task: work is left for it
    faults = {"bad_workers": ["w0"], "trace": str(trace), "wait_for_worker": {"w1": "w2"}}
    r = farm("submit", "-m", "uniform:12", *TINY, "--workers", "2", "-o", out, faults=faults)
    assert r.returncode == 0, r.stderr
    assert_exactly_once(out, 12)
    workers = job(out)["workers"]
    assert workers["w0"]["status"] == "blocklisted" and workers["w0"]["failures"] == 3
    assert "w2" in workers and workers["w2"]["frames"] > 0


def test_task_timeout_counts_as_failure(tmp_path):
    out = tmp_path / "set.zarr"
    r = farm(
        "submit",
        "-m",
        "uniform:2",
        *TINY,
        "--workers",
        "2",
        "--task-timeout",
        "2",
        "--max-attempts",
        "2",
        "-o",
        out,
        faults={"hang_materials": [0]},
    )
    assert r.returncode == 1
    f = job(out)["failures"]["0"]
    assert f["final"] and all("timed out" in e["error"] for e in f["errors"])


def test_node_removed_mid_job(tmp_path, monkeypatch):
    """A two-node Ray cluster on this machine; the node goes while its worker holds a task.

    The second node's raylet (and so its worker) sees a ``hold_while`` fault: its first task
    waits on a file that is never removed, and says so; the head's worker waits for that
    (``wait_for``), so it cannot finish the job first. The node goes mid-task however loaded
    the machine is, the head's worker takes that task over and the job ends whole."""
    monkeypatch.setenv("RAY_AUTH_MODE", "disabled")
    monkeypatch.delenv(FAULTS_ENV, raising=False)
    hold = tmp_path / "hold"
    hold.touch()
    cluster = local_cluster(1, {FAULTS_ENV: json.dumps({"wait_for": f"{hold}.held"})})
    node = add_local_node(cluster, 1, {FAULTS_ENV: json.dumps({"hold_while": str(hold)})})
    out = tmp_path / "set.zarr"
    args = ["submit", "-m", "uniform:8", *TINY, "--workers", "2", "-o", out]
    try:
        cluster.wait_for_nodes()
        proc = farm(*args, "--address", cluster.address, wait=False)
        try:
            held = Path(f"{hold}.held")
            wait_until(held.exists, 120, "the node's worker never got a task")
            cluster.remove_node(node)  # a machine of the farm disappears mid-task
            stdout, stderr = proc.communicate(timeout=240)
        finally:
            proc.kill()
        assert proc.returncode == 0, stderr
        assert_exactly_once(out, 8)
        workers = list(job(out)["workers"].values())
        dead = [w for w in workers if w["status"] == "dead"]
        # the held worker died with its one task, unrendered; the head's worker rendered all
        assert [(w["materials"], w["failures"]) for w in dead] == [(0, 1)], workers
        assert sum(w["materials"] for w in workers) == 8, workers
    finally:
        cluster.shutdown()


HOLD_ONE_CPU = """
import sys
from farm.cluster import ray_environment
ray_environment(sys.argv[1])
import ray
ray.init(address=sys.argv[1], _node_ip_address="127.0.0.1", log_to_driver=False)
holder = ray.remote(num_cpus=1)(type("Holder", (), {"ping": lambda self: 1})).remote()
ray.get(holder.ping.remote())
print("held", flush=True)
sys.stdin.read()
"""


def test_a_job_without_workers_given_grows_onto_a_node_that_joins(tmp_path, monkeypatch):
    """A two-CPU head where another Ray job holds one CPU, then a second node joins mid-job,
    as a scaled-up worker group's pod or an autoscaler's node would. The farm starts one
    worker, not one for each of the head's CPUs. That worker waits (``wait_for``) until a
    worker on the new node holds a task (``hold_while``'s file): the job cannot end unless
    the farm started one there."""
    monkeypatch.setenv("RAY_AUTH_MODE", "disabled")
    monkeypatch.delenv(FAULTS_ENV, raising=False)
    hold = tmp_path / "hold"
    hold.touch()
    held = Path(f"{hold}.held")
    cluster = local_cluster(2, {FAULTS_ENV: json.dumps({"wait_for": str(held)})})
    out = tmp_path / "set.zarr"
    other = subprocess.Popen([sys.executable, "-c", HOLD_ONE_CPU, cluster.address],
                             stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True)  # fmt: skip
    try:
        cluster.wait_for_nodes()
        assert other.stdout.readline().strip() == "held"  # another job holds one CPU
        proc = farm("submit", "-m", "uniform:6", *TINY, "-o", out,
                    "--address", cluster.address, wait=False)  # fmt: skip
        try:
            state = out / "farm" / "job.json"
            wait_until(lambda: state.exists() and any(
                w["status"] == "busy" for w in job(out)["workers"].values()
            ), 120, "the head's worker never got a task")  # fmt: skip
            assert len(job(out)["workers"]) == 1  # the one CPU the other job leaves free
            add_local_node(cluster, 1, {FAULTS_ENV: json.dumps({"hold_while": str(hold)})})
            wait_until(held.exists, 120, "no worker started on the node that joined")
            hold.unlink()
            stdout, stderr = proc.communicate(timeout=240)
        finally:
            proc.kill()
        assert proc.returncode == 0, stderr[-3000:]
        assert "the cluster holds 2 workers: starting 1 more" in stdout + stderr
        assert_exactly_once(out, 6)
        workers = list(job(out)["workers"].values())
        assert len(workers) == 2 and all(w["materials"] for w in workers), workers
    finally:
        other.kill()
        cluster.shutdown()


def test_workers_waiting_for_room_make_an_autoscaling_cluster_add_nodes(tmp_path, monkeypatch):
    """A cluster whose head has no CPUs, with Ray's autoscaler (``tests.ray_autoscaler``, set
    up as KubeRay's, with a CPU and a GPU node type). ``--workers 3`` on 2 materials starts 2
    workers (no node for a third that would have nothing to do); none fits anywhere until the
    autoscaler, seeing them wait, adds CPU nodes, one for each, and the job renders everything
    on them (each material takes 3 s: time for the second node to come up)."""
    from tests.ray_autoscaler import autoscaling_cluster

    out = tmp_path / "set.zarr"
    # the nodes' environment is the head's: the actors on them read the fault from there
    monkeypatch.setenv("SHADERBALL_FARM_FAULTS", json.dumps({"slow_s": 3}))
    with autoscaling_cluster(node_cpus=1, max_nodes=3) as (address, monitor_log):
        r = farm("submit", "-m", "uniform:2", *TINY, "--workers", "3",
                 "--placement-timeout", "120", "--address", address, "-o", out)  # fmt: skip
        added = re.findall(r"Adding (\d+) node\(s\) of type (\w+)", monitor_log.read_text())
    assert r.returncode == 0, r.stderr[-3000:]
    assert_exactly_once(out, 2)
    # nodes for the waiting workers (how many is the autoscaler's to say: it replaces a node
    # whose launch failed), CPU nodes only: none of the GPU type for CPU workers
    assert added and {kind for _, kind in added} == {"cpu"}, added
    assert "2 workers, room for 0 now: the others wait for room (an autoscaling" in r.stdout
    workers = job(out)["workers"].values()
    assert len(workers) == 2 and sum(w["materials"] for w in workers) == 2, workers
    # both placed: each stopped at the end, or released at the tail with nothing left to take
    assert {w["status"] for w in workers} <= {"stopped", "released"}, workers


class Output:
    """A running process's stdout and stderr, each read on a thread, for a test to wait on."""

    def __init__(self, proc: subprocess.Popen):
        self.proc, self.out, self.err = proc, [], []
        self.readers = [
            threading.Thread(target=self._read, args=(stream, lines), daemon=True)
            for stream, lines in [(proc.stdout, self.out), (proc.stderr, self.err)]
        ]
        for reader in self.readers:
            reader.start()

    @staticmethod
    def _read(stream, lines: list[str]) -> None:
        for line in stream:
            lines.append(line)

    def stdout(self) -> str:
        return "".join(self.out)

    def wait(self, timeout: float) -> tuple[int, str, str]:
        """The exit status, stdout and stderr once the process ends."""
        code = self.proc.wait(timeout)
        for reader in self.readers:
            reader.join(10)
        return code, self.stdout(), "".join(self.err)


IDLE_REMOVAL = "Removing 1 nodes of type cpu (idle)"


def traced_workers(trace: Path) -> set[str]:
    """The workers that the ``trace`` fault's file says started a task."""
    lines = trace.read_text().splitlines() if trace.exists() else []
    return {line.split()[0] for line in lines}


def plant_holds(tmp_path: Path, monkeypatch, held: list[int], **faults) -> tuple[Path, list]:
    """Faults in the environment that the autoscaler's nodes inherit: ``faults``, a trace, and
    a hold on each of the ``held`` materials (a file each, removed to let it go). Returns the
    trace's path and the hold files."""
    trace, holds = tmp_path / "trace", [tmp_path / f"hold-{m}" for m in held]
    for hold in holds:
        hold.touch()
    pairs = zip(holds, held, strict=True)
    faults["hold_materials"] = [{"while": str(h), "materials": [m]} for h, m in pairs]
    monkeypatch.setenv(FAULTS_ENV, json.dumps({**faults, "trace": str(trace)}))
    return trace, holds


@contextlib.contextmanager
def job_on_two_nodes(address: str, out: Path, materials: int, size: list[str], trace, first):
    """``farm submit --workers 2`` on ``materials`` on the autoscaling cluster at ``address``;
    yields its :class:`Output` once both workers have started a task (the ``first`` material
    held meanwhile, so that the first worker cannot render everything before the second node
    comes up) and the first material is let go; kills the job at the end."""
    args = ["-m", f"uniform:{materials}", *size, "--workers", "2", "--no-ray-dashboard"]
    args += ["--placement-timeout", "120", "--address", address, "-o", out]
    proc = farm("submit", *args, wait=False)
    try:
        output = Output(proc)

        def two() -> bool:
            if proc.poll() is not None:  # say why, not that the worker never came
                code, _, stderr = output.wait(10)
                raise AssertionError(f"the job ended (exit {code}) early: {stderr[-2000:]}")
            return len(traced_workers(trace)) == 2

        wait_until(two, 150, "the second worker never started a task")
        first.unlink()
        yield output
    finally:
        proc.kill()


def test_the_node_of_a_worker_released_at_the_tail_is_taken_down_while_the_job_renders(
    tmp_path, monkeypatch
):
    """``--workers 2`` on 3 materials on the autoscaling cluster (3 s idle timeout): the first
    is held until the other worker has started a task, and the last until a node has been
    taken down. The worker left idle at the tail is released, and its node goes while the
    other worker still renders the last material."""
    from tests.ray_autoscaler import autoscaling_cluster

    out = tmp_path / "set.zarr"
    trace, (first, last) = plant_holds(tmp_path, monkeypatch, [0, 2])
    with (
        autoscaling_cluster(node_cpus=1, max_nodes=2, idle_timeout_s=3) as (address, log),
        job_on_two_nodes(address, out, 3, TINY, trace, first) as output,
    ):
        wait_until(lambda: IDLE_REMOVAL in log.read_text(), 90, "no node taken down")
        last.unlink()  # the last material renders only now
        code, stdout, stderr = output.wait(120)
    assert code == 0, stderr[-3000:]
    assert "0 tasks queued, 1 running: releasing 1 idle worker (w" in stdout
    assert sorted(w["status"] for w in job(out)["workers"].values()) == ["released", "stopped"]
    assert_exactly_once(out, 3)


#: how long the kept-node test holds the job after the release: five idle timeouts
KEPT_S = 15


def test_a_released_workers_node_holding_uncommitted_results_is_kept(tmp_path, monkeypatch):
    """2 materials in one shard at 128² (their arrays, about 0.4 MB each, live in the object
    store of the worker's node, not inline in the driver), one on each worker: the first is
    held until the second has started on the other worker, so that the two run on two nodes. The
    worker that rendered the first is released, but its results wait for the shard's commit,
    held ``KEPT_S`` seconds after the release (the second material's hold): the autoscaler (3
    s idle timeout) does not take its node down (Ray keeps a node holding the primary copy of
    an object), and nothing is rendered twice."""
    from tests.ray_autoscaler import autoscaling_cluster

    out = tmp_path / "set.zarr"
    trace, (first, second) = plant_holds(tmp_path, monkeypatch, [0, 1])
    size = ["--suns", "2", "--shard-size", "4", "--resolution", "128", "--samples", "2"]
    released = "0 tasks queued, 1 running: releasing 1 idle worker (w"
    with (
        autoscaling_cluster(node_cpus=1, max_nodes=2, idle_timeout_s=3) as (address, log),
        job_on_two_nodes(address, out, 2, size, trace, first) as output,
    ):
        wait_until(lambda: released in output.stdout(), 60, "no worker released")
        time.sleep(KEPT_S)
        second.unlink()
        code, stdout, stderr = output.wait(120)
        monitor = log.read_text()
    assert code == 0, stderr[-3000:]
    workers = job(out)["workers"].values()
    assert sorted((w["status"], w["materials"]) for w in workers) == [
        ("released", 1), ("stopped", 1)
    ], workers  # fmt: skip
    # the node may go once the shard is committed (the job's shutdown can outlast the idle
    # timeout), not before
    committed_at = (out / "commits" / "000000.json").stat().st_mtime
    assert idle_removals_before(monitor, committed_at) == [], monitor[-3000:]
    assert "materials were lost" not in stderr
    assert_exactly_once(out, 2)


def idle_removals_before(monitor: str, t: float) -> list[str]:
    """The lines of the autoscaler's log ``monitor`` that remove an idle node, logged before
    the time ``t`` (each dated by the last timestamped line at or above it)."""
    stamp, out = None, []
    for line in monitor.splitlines():
        if m := re.match(r"(\d{4}-\d\d-\d\d \d\d:\d\d:\d\d),(\d{3})", line):
            stamp = datetime.strptime(m[1], "%Y-%m-%d %H:%M:%S").timestamp() + int(m[2]) / 1e3
        if IDLE_REMOVAL in line and (stamp is None or stamp < t):
            out.append(line)
    return out


def kill_the_nodes_but_that_of(out, worker: str) -> int:
    """Kill (SIGKILL) the raylets, and what they started, of the autoscaler's nodes other than
    the one ``worker`` of the job at ``out`` runs on (its pid from the job state); how many
    nodes were killed."""
    deadline = time.time() + 30
    while (pid := job(out)["workers"][worker].get("pid")) is None and time.time() < deadline:
        time.sleep(0.2)  # the state is saved every few seconds
    mine = next(p for p in psutil.Process(pid).parents() if p.name() == "raylet")
    raylets = [p for p in psutil.process_iter(["name"]) if p.info["name"] == "raylet"]
    victims = [r for r in raylets if r.ppid() == mine.ppid() and r.pid != mine.pid]
    for raylet in victims:  # the autoscaler (their parent) launched every node
        for proc in [*raylet.children(recursive=True), raylet]:
            with contextlib.suppress(psutil.NoSuchProcess):  # ended meanwhile
                proc.kill()
    return len(victims)


def test_results_lost_with_a_node_after_a_release_are_rendered_again(tmp_path, monkeypatch):
    """8 materials in one shard at 128² (their arrays in the object store of their worker's
    node), the first held until both workers have a task, the last 12 s slower, ``--workers
    2``: the worker idle at the tail is released, then its node dies (killed here, as a node
    lost to a preemption) with the results waiting for the shard's commit. The commit finds
    them lost: the materials whose results were on that node, and only those, are queued
    again, and the job starts a worker again at once (up to its --workers) for those the
    idle worker left will not take; it ends with every sample once."""
    from tests.ray_autoscaler import autoscaling_cluster

    out = tmp_path / "set.zarr"
    # material 0 waits until both workers render: each then holds results
    trace, (first,) = plant_holds(tmp_path, monkeypatch, [0], slow_s=0.5, slow_materials={"7": 12})
    size = ["--suns", "2", "--shard-size", "16", "--resolution", "128", "--samples", "2"]
    with (
        autoscaling_cluster(node_cpus=1, max_nodes=2) as (address, _),
        job_on_two_nodes(address, out, 8, size, trace, first) as output,
    ):
        released = lambda: re.search(r"releasing 1 idle worker \((w\d)\)", output.stdout())  # noqa: E731
        wait_until(released, 120, "no worker released")
        other = {"w0": "w1", "w1": "w0"}[released().group(1)]
        assert kill_the_nodes_but_that_of(out, other) == 1
        code, stdout, err = output.wait(240)
    assert code == 0, err[-3000:]
    said = re.search(r"shard 0: the results of (\d+) of its 8 materials were lost", err)
    assert said, stdout + err[-2000:]
    lost = int(said.group(1))  # what the released worker rendered; the other's are kept
    assert 1 <= lost < 8, err[-2000:]
    if lost > 1:  # more than the worker left, idle then, takes at once
        assert f"{lost} tasks queued: starting 1 worker again (--workers 2)" in stdout, stdout
    assert_exactly_once(out, 8)
    workers = job(out)["workers"].values()
    assert "released" in [w["status"] for w in workers]
    assert sum(w["materials"] for w in workers) == 8 + lost  # none kept rendered twice


def test_killed_driver_resumes_where_it_stopped(tmp_path):
    out = tmp_path / "set.zarr"
    args = ["submit", "-m", "uniform:10", *TINY, "--workers", "2", "-o", out]
    # material 9 (the last shard's) keeps the job running until the signal
    proc = farm(*args, faults={"slow_materials": {"9": 60}}, wait=False, ray_dashboard=True)
    ray = []
    try:
        wait_for_commits(out, 2)
        ray = psutil.Process(proc.pid).children(recursive=True)  # the embedded Ray
        proc.send_signal(signal.SIGKILL)  # the driver dies mid-job
        proc.wait(30)
    finally:
        proc.kill()
        for p in ray:  # the dead driver's Ray, and only it
            with contextlib.suppress(psutil.NoSuchProcess):
                p.kill()
    done_before = len(Store(str(out)).committed_shards())
    assert 2 <= done_before < 5
    # the dead driver's state still says running, but its lease names a process gone from
    # this machine: `farm status` calls the job lost at once and says what to do
    assert json.loads((Path(out) / "farm" / "job.json").read_text())["status"] == "running"
    s = farm("status", out)
    assert s.returncode == 0 and "lost: says running" in s.stdout and "farm submit" in s.stdout
    assert json.loads(farm("status", out, "--json").stdout)["effective_status"] == "lost"
    r = farm(*args, "--no-ray-dashboard")  # how to run is not part of the dataset
    assert r.returncode == 0, r.stderr
    assert "ray dashboard: off" in r.stdout
    assert f"resuming: {done_before} of 5 shards already committed" in r.stdout
    assert f"{20 - 4 * done_before} rendered, {4 * done_before} already there" in r.stdout
    assert_exactly_once(out, 10)


def test_a_job_state_is_saved_as_the_job_starts_before_any_shard_is_committed(tmp_path):
    """``farm status`` sees a running job from its start: its state is written as the workers
    start, not at the loop's first periodic save, so it is there when the first task starts
    (a tiny job's shards can be committed within that period) and a driver killed before
    any save after its commits still leaves a state that ``farm status`` can call lost."""
    out, hold = tmp_path / "set.zarr", tmp_path / "hold"
    hold.touch()  # every task waits while it exists, after saying so in hold.held
    proc = farm("submit", "-m", "uniform:2", *TINY, "-o", out, faults={"hold_while": str(hold)},
                wait=False)  # fmt: skip
    try:
        wait_until(Path(f"{hold}.held").exists, 120, "no task started")
        assert job(out)["status"] == "running" and job(out)["shards_total"] == 1
        assert not list((out / "commits").glob("*.json"))
        proc.send_signal(signal.SIGTERM)
        proc.communicate(timeout=90)
    finally:
        proc.kill()
    assert job(out)["status"] == "interrupted"


def test_sigterm_stops_the_job_cleanly_and_the_same_command_resumes(tmp_path):
    """What a deleted pod, ``timeout`` or ``docker stop`` sends: the driver stops its workers
    and Ray, says how to resume and exits 143; the job state says interrupted, not running."""
    out = tmp_path / "set.zarr"
    args = ["submit", "-m", "uniform:10", *TINY, "--workers", "2", "-o", out]
    # material 9 (the last shard's) keeps the job running until the signal
    proc = farm(*args, faults={"slow_materials": {"9": 60}}, wait=False)
    try:
        wait_for_commits(out, 1)
        proc.send_signal(signal.SIGTERM)
        _, err = proc.communicate(timeout=90)
    finally:
        proc.kill()
    assert proc.returncode == 128 + signal.SIGTERM, err[-2000:]
    assert f"SIGTERM: stopped; every committed shard is kept (farm status {out})" in err
    st = job(out)
    assert st["status"] == "interrupted"
    workers = [w["pid"] for w in st["workers"].values() if w["pid"]]
    assert workers

    def gone() -> bool:  # the embedded Ray went down with the driver
        return not any(psutil.pid_exists(pid) for pid in workers)

    wait_until(gone, 10, f"render workers {workers} outlived the driver")
    r = farm(*args)
    assert r.returncode == 0, r.stderr
    assert "resuming: " in r.stdout
    assert_exactly_once(out, 10)


def test_a_sigterm_during_a_finished_jobs_clean_up_waits_for_it(tmp_path):
    """SIGTERM while the driver stops its workers after the last commit: the clean-up ends
    (state saved as done, Ray shut down), then the driver stops as asked."""
    out, closing = tmp_path / "set.zarr", tmp_path / "closing"
    faults = {"closing": str(closing), "close_s": 5}
    proc = farm("submit", "-m", "uniform:2", *TINY, "-o", out, faults=faults, wait=False)
    try:
        wait_until(closing.exists, 120, "no worker was asked to close")
        ours = psutil.Process(proc.pid).children(recursive=True)  # Ray's, its workers
        proc.send_signal(signal.SIGTERM)
        _, err = proc.communicate(timeout=90)
    finally:
        proc.kill()
    assert proc.returncode == 128 + signal.SIGTERM, err[-2000:]
    assert err.strip().splitlines()[-1].startswith("SIGTERM: stopped; every committed shard")
    assert job(out)["status"] == "done"
    assert_exactly_once(out, 2)
    wait_until(lambda: all(_dead(p) for p in ours), 10, "Ray outlived the driver")


def test_a_farm_job_over_a_flaky_object_store_commits_every_sample_once(s3, tmp_path):
    """``--out s3://...`` through a proxy that answers 503 SlowDown or resets the connection
    on four writes, one in every 12, for more tries of each than s3fs makes (botocore's own
    retries off): the project's retries are logged, the job ends whole, with the same data as
    the same job written locally; a bucket that denies access fails at once."""
    endpoint, opts = s3
    args = ["submit", "-m", "uniform:4", *TINY, "--workers", "1"]
    with FlakyProxy.past_client_retries(
        endpoint, every=12, method="PUT", deny="/denied.zarr"
    ) as proxy:
        env = s3_env(proxy.endpoint, AWS_MAX_ATTEMPTS="1", AWS_RETRY_MODE="standard")
        r = farm(*args, "-o", "s3://shaderball/farm.zarr", env=env)
        assert r.returncode == 0, r.stderr[-3000:]
        t0 = time.time()
        denied = farm(*args, "-o", "s3://shaderball/denied.zarr", env=env)
        assert time.time() - t0 < 60
    assert proxy.faults["503"] and proxy.faults["reset"], proxy.faults
    assert "retry 1 in" in r.stderr
    assert denied.returncode == 1 and "Traceback" not in denied.stderr
    assert denied.stderr.strip().splitlines()[-1].startswith("Error: s3://shaderball/denied.zarr")
    local = tmp_path / "local.zarr"
    assert farm(*args, "-o", local).returncode == 0
    remote, here = Store("s3://shaderball/farm.zarr", opts), Store(str(local))
    assert remote.committed_shards() == here.committed_shards() == [0, 1]
    for name in ("seed", "material_index", "sun_direction", "turbidity"):
        np.testing.assert_array_equal(remote.group[name][:], here.group[name][:])
    np.testing.assert_array_equal(remote.group["maps"][:], here.group["maps"][:])
    assert verify(remote).ok


def test_an_object_store_out_of_reach_fails_in_one_line_after_one_round_of_retries(tmp_path):
    """An S3 endpoint nobody listens on: the submit ends, after the retries, with one line
    that names the store, having retried one operation: the lease for a generated job, the
    store's committed shards (read before its materials are validated) for a file one."""
    from tests.conftest import free_port
    from tests.test_material_libraries import ambientcg

    env = s3_env(f"http://127.0.0.1:{free_port()}", AWS_MAX_ATTEMPTS="1",
                 SHADERBALL_STORE_RETRY_S="2")  # fmt: skip
    for material in ("uniform:2", f"svbrdf:{ambientcg(tmp_path)}"):
        r = farm("submit", "-m", material, *TINY, "-o", "s3://shaderball/gone.zarr", env=env)
        assert r.returncode == 1 and "Traceback" not in r.stderr, r.stderr[-3000:]
        last = r.stderr.strip().splitlines()[-1]
        assert last.startswith("Error: s3://shaderball/gone.zarr: StoreUnreachable: "), last
        assert "EndpointConnectionError" in last and "validating" not in r.stderr
        assert r.stderr.count("retry 1 in") == 1, r.stderr


def test_the_embedded_farm_starts_its_own_ray_beside_a_running_cluster(tmp_path):
    """Without --address or RAY_ADDRESS the farm starts its own local Ray, even while a
    cluster started on the same machine runs (with no address Ray would join that one)."""
    cluster = local_cluster(1)
    saved = os.environ.pop("RAY_ADDRESS", None)
    try:
        out = tmp_path / "own.zarr"
        r = farm("submit", "-m", "uniform:1", *TINY, "--workers", "1",
                 "-o", out)  # fmt: skip
        assert r.returncode == 0, r.stderr[-2000:]
        assert_exactly_once(out, 1)
    finally:
        if saved is not None:
            os.environ["RAY_ADDRESS"] = saved
        cluster.shutdown()
