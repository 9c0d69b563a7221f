"""``trainer launch``: torchrun around ``trainer train``, on one node or many.

One node (the default) uses torchrun's ``--standalone`` rendezvous; several nodes use c10d
rendezvous at ``--rdzv-endpoint HOST:PORT`` (every node runs the same command, and the
rendezvous ranks the nodes: torchrun ignores a node rank there, with a warning, so none is
passed; the launcher prints the command for the others), or torchrun's static rendezvous at
``--master-addr``/``--master-port`` (each node with its ``--node-rank``; rank 0 hosts it).
The static form is what Kubeflow Trainer's ``torch-distributed`` runtime gives each pod, as
``PET_NNODES``, ``PET_NODE_RANK``, ``PET_MASTER_ADDR``, ``PET_MASTER_PORT`` and
``PET_NPROC_PER_NODE``, which the CLI reads when its flags are not given. torchrun restarts all
ranks when one fails (``--max-restarts``); a restarted rank resumes from the run folder's
latest checkpoint (``TORCHELASTIC_RESTART_COUNT`` > 0 implies ``--resume``).
"""

from __future__ import annotations

import shlex
import sys
import tempfile
from dataclasses import dataclass

import torch

from shaderball.errors import UserError
from trainer.training.config import TrainConfig, to_argv


@dataclass(frozen=True)
class LaunchConfig:
    nodes: int = 1
    nproc_per_node: int | None = None  # None: all local GPUs, or 1 process on CPU
    rdzv_endpoint: str | None = None
    node_rank: int | None = None
    max_restarts: int = 0
    rdzv_id: str = "shaderball"
    master_addr: str | None = None  # static rendezvous (Kubeflow's PET_MASTER_ADDR)
    master_port: int = 29400

    def __post_init__(self) -> None:
        if self.nodes < 1:
            raise ValueError(f"--nodes must be at least 1, not {self.nodes}")
        if self.nodes > 1 and not (self.rdzv_endpoint or self.master_addr):
            raise ValueError(
                "several nodes need --rdzv-endpoint HOST:PORT or --master-addr HOST "
                "(reachable by all)"
            )
        if self.master_addr and self.node_rank is None:
            raise ValueError("--master-addr needs --node-rank (0 hosts the rendezvous)")
        if self.rdzv_endpoint and ":" not in self.rdzv_endpoint:
            raise ValueError(f"--rdzv-endpoint {self.rdzv_endpoint!r} is not HOST:PORT")
        if self.node_rank is not None and not 0 <= self.node_rank < self.nodes:
            raise ValueError(f"--node-rank {self.node_rank} is not in 0..{self.nodes - 1}")

    def procs(self) -> int:
        if self.nproc_per_node is not None:
            return self.nproc_per_node
        return max(torch.cuda.device_count(), 1)


def torchrun_argv(launch: LaunchConfig, cfg: TrainConfig, node_rank: int | None = None) -> list:
    """The torchrun command line for one node."""
    argv = [sys.executable, "-m", "torch.distributed.run"]
    if launch.master_addr:
        rank = launch.node_rank if node_rank is None else node_rank
        argv += ["--nnodes", str(launch.nodes), "--node-rank", str(rank)]
        argv += ["--master-addr", launch.master_addr, "--master-port", str(launch.master_port)]
    elif launch.nodes == 1 and not launch.rdzv_endpoint:
        argv += ["--standalone", "--nnodes", "1"]
    else:
        argv += ["--nnodes", str(launch.nodes), "--rdzv-backend", "c10d"]
        argv += ["--rdzv-endpoint", launch.rdzv_endpoint, "--rdzv-id", launch.rdzv_id]
    argv += ["--nproc-per-node", str(launch.procs()), "--max-restarts", str(launch.max_restarts)]
    return [*argv, "-m", "trainer.cli", "train", *to_argv(cfg)]


def other_node_commands(launch: LaunchConfig, cfg: TrainConfig) -> list[str]:
    """``trainer launch`` lines to run on the other nodes of a multi-node job: one a node for
    the static rendezvous (each its rank), one for them all for c10d."""
    here = launch.node_rank or 0
    ranks = [r for r in range(launch.nodes) if r != here] if launch.master_addr else [None]
    out = []
    for r in ranks:
        args = ["trainer", "launch", "--nodes", str(launch.nodes)]
        if launch.nproc_per_node is not None:
            args += ["--nproc-per-node", str(launch.nproc_per_node)]
        if launch.master_addr:
            args += ["--master-addr", launch.master_addr, "--master-port"]
            args += [str(launch.master_port), "--node-rank", str(r)]
        else:
            args += ["--rdzv-endpoint", launch.rdzv_endpoint]
        args += ["--max-restarts", str(launch.max_restarts), *to_argv(cfg)]
        out.append(shlex.join(args))
    return out


class RankFailed(UserError, RuntimeError):
    """A rank of the torchrun job failed (after any restarts)."""


def run_torchrun(argv: list[str]) -> None:
    """Run the torchrun command ``argv`` (as :func:`torchrun_argv` makes it) in this process,
    as ``python -m torch.distributed.run`` would: its elastic agent starts and watches the
    ranks, and stops them on SIGINT / SIGTERM (this process then exits 128 + the signal). A
    failed job raises :class:`RankFailed` naming the first failed rank, in place of torchrun's
    traceback; the rank printed its own error.

    The agent's log folder (the ranks' error files) is a temporary folder removed when the
    job ends, however it ends: torchrun makes one per job under $TMPDIR and leaves it."""
    from torch.distributed.elastic.multiprocessing.api import SignalException
    from torch.distributed.elastic.multiprocessing.errors import ChildFailedError
    from torch.distributed.run import parse_args, run

    args = parse_args(argv[3:])  # after "python -m torch.distributed.run"
    try:
        with tempfile.TemporaryDirectory(prefix="torchelastic_") as logs:
            args.log_dir = args.log_dir or logs
            run(args)
    except SignalException as exc:  # the agent has stopped the ranks; leave as the signal says
        raise SystemExit(128 + int(exc.sigval)) from None
    except ChildFailedError as exc:
        rank, failure = min(exc.failures.items())
        raise RankFailed(
            f"rank {rank} of the torchrun job failed with exit code {failure.exitcode} "
            f"(its error is above; {len(exc.failures)} rank(s) failed)"
        ) from None
