"""Multi-node Ray clusters on this machine (``ray.cluster_utils.Cluster``) for the tests.

Every node listens on the loopback interface. The head starts without Ray's dashboard: no
test reads it, and on a 2-core machine it costs each cluster seconds of start-up and CPU
beside the work (the farm's own default, an embedded Ray with its dashboard, is tested in
``tests/test_farm.py::test_submit_resume_and_refusal``).
"""

from __future__ import annotations

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
