"""A Ray cluster on 127.0.0.1 with Ray's own autoscaler, for the tests.

The head has no CPUs and runs Ray's autoscaler (``ray start --autoscaling-config``) with its
``fake_multinode`` node provider: a node the autoscaler launches is a real raylet process on
this machine instead of a VM or a pod. The provider is set up as KubeRay's autoscaler sets up
its own (no node updaters, no launch config check, nodes launched in the foreground), so a
job sees what it would see on a KubeRay cluster with ``enableInTreeAutoscaling``: workers that
wait for room make the autoscaler add nodes, up to ``max_nodes``, and a node idle for
``idle_timeout_s`` is taken down. The nodes are told apart by their node IDs, as they share
one IP address.

The head runs in a process group of its own, and everything it started, the nodes the
autoscaler launched included, is killed with that group: no ``ray stop``, which would stop
every Ray on the machine.
"""

from __future__ import annotations

import contextlib
import json
import os
import tempfile
import time
from collections.abc import Iterator
from pathlib import Path

from tests.conftest import free_port
from tests.ray_local import ray_head

NO_SETUP = (  # the autoscaler's cluster-launcher keys, which a KubeRay cluster leaves empty
    "initialization_commands", "setup_commands", "head_setup_commands",
    "worker_setup_commands", "head_start_ray_commands", "worker_start_ray_commands",
    "cluster_synced_files",
)  # fmt: skip


def config(address: str, node_cpus: int, max_nodes: int, idle_timeout_s: float = 300) -> dict:
    """The autoscaler's cluster config: a head with no CPUs, a ``cpu`` node type of
    ``node_cpus`` and a ``gpu`` one of as many CPUs and a GPU (declared: Ray takes a node's
    word for its GPUs), as k8s/base/raycluster.yaml has a CPU and a GPU worker group."""
    node = {"node_config": {}, "min_workers": 0, "max_workers": max_nodes}
    return {
        "cluster_name": "shaderball-test",
        "max_workers": 2 * max_nodes,
        "upscaling_speed": 1.0,
        "idle_timeout_minutes": idle_timeout_s / 60,
        "provider": {
            "type": "fake_multinode",
            "gcs_address": address,
            "disable_node_updaters": True,
            "disable_launch_config_check": True,
            "foreground_node_launch": True,
            # without it the provider starts one node for a launch of several, which the
            # autoscaler counts as all started: a job asking for 2 nodes got 1
            "launch_multiple": True,
            # every node is on 127.0.0.1: without it the autoscaler's load metrics, keyed by
            # IP address, cannot tell them apart and it sees none of them up or idle
            "use_node_id_as_ip": True,
        },
        "auth": {"ssh_user": "ray"},
        "head_node_type": "ray.head.default",
        "available_node_types": {
            "ray.head.default": {"resources": {"CPU": 0}, "node_config": {}, "max_workers": 0},
            "cpu": {"resources": {"CPU": node_cpus}, **node},
            "gpu": {"resources": {"CPU": node_cpus, "GPU": 1}, **node},
        },
        "file_mounts": {},
        "file_mounts_sync_continuously": False,
        **{key: [] for key in NO_SETUP},
    }


@contextlib.contextmanager
def autoscaling_cluster(
    node_cpus: int = 1, max_nodes: int = 2, idle_timeout_s: float = 300
) -> Iterator[tuple[str, Path]]:
    """Start the cluster; yields its address and the autoscaler's log (``monitor.log``). A
    node idle for ``idle_timeout_s`` is taken down."""
    port = free_port()
    address = f"127.0.0.1:{port}"
    # short: Ray's socket paths under it must fit in a Unix socket address (107 bytes)
    temp = Path(tempfile.mkdtemp(prefix="ray-as-", dir="/tmp"))
    cfg = config(address, node_cpus, max_nodes, idle_timeout_s)
    (temp / "autoscaler.json").write_text(json.dumps(cfg))
    env = {**os.environ, "RAY_FAKE_CLUSTER": "1", "AUTOSCALER_UPDATE_INTERVAL_S": "1",
           "RAY_ENABLE_WINDOWS_OR_OSX_CLUSTER": "0", "RAY_AUTH_MODE": "disabled",
           "RAY_worker_niceness": "0"}  # as k8s/base/raycluster.yaml sets it  # fmt: skip
    args = ["--num-cpus", "0", "--autoscaling-config", temp / "autoscaler.json",
            "--node-ip-address", "127.0.0.1"]  # fmt: skip
    with ray_head(args, env, temp, port):
        yield address, monitor_log(temp / "session_latest" / "logs" / "monitor.log")


def monitor_log(log: Path, timeout: float = 60) -> Path:
    """``log`` once the autoscaler has made it: the head answers before its monitor process
    has opened the file, and a test reading it at once found none."""
    deadline = time.time() + timeout
    while not log.exists():
        if time.time() > deadline:
            raise RuntimeError(f"the autoscaler wrote no {log} in {timeout:.0f} s")
        time.sleep(0.2)
    return log
