"""Multi-node Ray clusters on this machine (``ray.cluster_utils.Cluster``) for the tests.

Every node listens on the loopback interface. The head starts without Ray's dashboard: no
test reads it, and on a 2-core machine it costs each cluster seconds of start-up and CPU
beside the work (the farm's own default, an embedded Ray with its dashboard, is tested in
``tests/test_farm.py::test_submit_resume_and_refusal``).
"""

from __future__ import annotations

import contextlib
import os
import shutil
import signal
import subprocess
import tempfile
from collections.abc import Iterator
from pathlib import Path

from tests.conftest import BIN, free_port, wait_for_port

LOOPBACK = {"node_ip_address": "127.0.0.1"}


def local_cluster(head_cpus: int, env_vars: dict[str, str] | None = None):
    """A running head with ``head_cpus`` CPUs; ``env_vars`` reach its workers."""
    from ray.cluster_utils import Cluster

    head = {"num_cpus": head_cpus, "include_dashboard": False, **LOOPBACK}
    if env_vars:
        head["env_vars"] = env_vars
    return Cluster(initialize_head=True, head_node_args=head)


def add_local_node(cluster, cpus: int, env_vars: dict[str, str] | None = None):
    """A node of ``cpus`` CPUs joined to ``cluster``; ``env_vars`` reach its workers."""
    return cluster.add_node(
        num_cpus=cpus, **({"env_vars": env_vars} if env_vars else {}), **LOOPBACK
    )


@contextlib.contextmanager
def ray_head(args: list, env: dict, temp: Path, port: int | None = None) -> Iterator[str]:
    """``ray start --head --block`` with ``args`` (more options), in a session of its own,
    on ``port`` (a free one if none), with ``temp`` as its temporary folder (removed after);
    yields ``127.0.0.1:PORT`` once the head answers. Killed at the end, not stopped: ``ray
    stop`` stops every Ray on the machine, and Ray's graceful stop takes about 30 s."""
    port = port or free_port()
    head = subprocess.Popen(
        [BIN / "ray", "start", "--head", "--block", "--port", str(port), *args,
         "--include-dashboard", "false", "--temp-dir", temp,
         "--ray-client-server-port", str(free_port()),
         "--dashboard-agent-listen-port", str(free_port())],
        env=env, start_new_session=True, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
    )  # fmt: skip
    try:
        if not wait_for_port(port, head, 60):
            raise RuntimeError(f"the Ray head on port {port} did not start")
        yield f"127.0.0.1:{port}"
    finally:
        with contextlib.suppress(ProcessLookupError):
            os.killpg(head.pid, signal.SIGKILL)
        head.wait(10)
        shutil.rmtree(temp, ignore_errors=True)


@contextlib.contextmanager
def ray_start_head(cpus: int) -> Iterator[str]:
    """A head started as people start one, ``ray start --head``, with Ray's defaults: the
    machine's outward address (127.0.0.1 on a machine with none), token authentication with
    the token in ``~/.ray/auth_token`` (which ``pytest_configure`` makes sure of); without
    the dashboard. Yields ``127.0.0.1:PORT``."""
    temp = Path(tempfile.mkdtemp(prefix="ray-h-", dir="/tmp"))  # Unix socket paths: short
    drop = ("RAY_AUTH_MODE", "RAY_ADDRESS", "RAY_ENABLE_WINDOWS_OR_OSX_CLUSTER")
    env = {k: v for k, v in os.environ.items() if k not in drop}
    with ray_head(["--num-cpus", str(cpus), "--disable-usage-stats"], env, temp) as address:
        yield address
