"""Chaos: one farm job through every fault at once, and nothing lost or written twice.

A three-node Ray cluster on this machine, the store on the local S3 server behind the flaky
proxy (503s and reset connections); the first 3 shards are committed, then, in turn: a
render actor's process killed, a whole node removed, the driver killed, each mid-task. The
same `farm submit` run again finishes the job on what is left, and the store is whole: every
sample once, with the seed its (material, sun) must have, and `shards verify` clean.

A planted hold (``hold_materials``, :mod:`farm.faults`) makes each fault land where it must,
however fast or slow the machine: the materials of the shards after the first 3 wait until
the driver has been killed, so every worker has a task in flight, and more wait in the
queue, when the faults land, and the job cannot end before them.
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import time

import numpy as np
import psutil
import pytest

from farm.state import load_state
from render_jobs.specs import derive_seed
from storage.reader import Store
from tests.conftest import s3_env
from tests.flaky_proxy import FlakyProxy
from tests.ray_local import add_local_node, local_cluster
from tests.test_farm import BIN, TINY, descendants, farm

pytestmark = pytest.mark.slow
URL = "s3://shaderball/chaos.zarr"
MATERIALS = 18  # 9 shards of 2 materials x 2 suns
SHARDS = MATERIALS // 2
FIRST = 3  # shards committed before the faults


def committed(opts: dict) -> int:
    try:
        return len(Store(URL, opts).committed_shards())
    except Exception:  # noqa: BLE001 - the store may not exist yet
        return 0


def dead_workers(opts: dict) -> int:
    """Workers the running driver has recorded as dead (its job state)."""
    state = load_state(URL, opts)
    return sum(w["status"] == "dead" for w in state["workers"].values()) if state else 0


def wait_until(test, timeout: float = 180):
    """``test()``'s first true value, asked every 0.3 s; fail after ``timeout``."""
    deadline = time.time() + timeout
    while time.time() < deadline:
        if got := test():
            return got
        time.sleep(0.3)
    raise AssertionError("timed out waiting for the job")


def render_actors(root: int | None = None) -> list[psutil.Process]:
    """The render actors under ``root`` (a node's raylet), or of this test's whole cluster
    (whose nodes this process started)."""
    return descendants(root or os.getpid(), "ray::RenderWorker")


def a_busy_actor(opts: dict, root: int | None = None) -> psutil.Process | None:
    """A render actor (under ``root``) that the running driver's job state says is
    rendering, and is alive."""
    state = load_state(URL, opts) or {"workers": {}}
    mine = {p.pid: p for p in render_actors(root)}
    busy = [w["pid"] for w in state["workers"].values() if w["status"] == "busy"]
    return next((mine[pid] for pid in busy if pid in mine), None)


def test_a_job_through_kills_a_lost_node_a_flaky_store_and_a_killed_driver(
    s3, monkeypatch, tmp_path
):
    endpoint, opts = s3
    args = ["submit", "-m", f"uniform:{MATERIALS}", *TINY, "--workers", "3"]
    hold = tmp_path / "hold"
    hold.touch()
    held = list(range(2 * FIRST, MATERIALS))  # the materials of the shards after the first
    faults = {"hold_materials": {"while": str(hold), "materials": held}}
    with FlakyProxy.past_client_retries(endpoint, every=25, method="PUT") as proxy:
        env = s3_env(
            proxy.endpoint,
            RAY_AUTH_MODE="disabled",
            AWS_MAX_ATTEMPTS="1",  # botocore's own retries off
            SHADERBALL_FARM_FAULTS=json.dumps(faults),
        )
        for k, v in env.items():  # the nodes' workers (and commit tasks) inherit these
            monkeypatch.setenv(k, v)
        cluster = local_cluster(1)
        add_local_node(cluster, 1)
        doomed = add_local_node(cluster, 1)
        try:
            cluster.wait_for_nodes()
            argv = [*args, "--address", cluster.address, "--no-ray-dashboard", "-o", URL]
            first = farm(*argv, env=env, wait=False)
            try:
                wait_until(lambda: committed(opts) == FIRST)
                wait_until(lambda: len(render_actors()) == 3)
                victim = wait_until(lambda: a_busy_actor(opts))
                victim.send_signal(signal.SIGKILL)  # a render actor dies mid-task
                wait_until(lambda: dead_workers(opts) >= 1)  # the driver saw it
                raylet = doomed.all_processes["raylet"][0].process.pid
                wait_until(lambda: a_busy_actor(opts, raylet))  # its worker has a task
                cluster.remove_node(doomed)  # a machine of the farm goes away
                wait_until(lambda: dead_workers(opts) >= 2)
                first.send_signal(signal.SIGKILL)  # and the driver itself
                first.wait(30)
            finally:
                first.kill()
            before = committed(opts)
            assert before == FIRST  # the driver was killed mid-job
            hold.unlink()
            second = farm(*argv, env=env, timeout=300)
        finally:
            cluster.shutdown()
    assert second.returncode == 0, second.stderr[-3000:]
    assert f"resuming: {before} of {SHARDS} shards already committed" in second.stdout
    assert proxy.faults["503"] and proxy.faults["reset"], proxy.faults
    store = Store(URL, opts)
    assert store.committed_shards() == list(range(SHARDS))
    want = [derive_seed(0, m, k) for m in range(MATERIALS) for k in range(2)]
    np.testing.assert_array_equal(store.group["seed"][:], want)
    np.testing.assert_array_equal(store.group["material_index"][:], np.repeat(range(MATERIALS), 2))
    check = {**env, "AWS_ENDPOINT_URL": endpoint, "AWS_MAX_ATTEMPTS": "3"}
    r = subprocess.run(
        [str(BIN / "shards"), "verify", URL], capture_output=True, text=True, env=check
    )
    assert r.returncode == 0, r.stdout + r.stderr
