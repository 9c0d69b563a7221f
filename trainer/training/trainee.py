"""What one rank of a training run holds: where it trains (:class:`Rank`) and the network
with everything its checkpoints keep (:class:`Trainee`). Plain data, shared by the loop
(``trainer.training.train``) and its log (``trainer.training.runlog``)."""

from __future__ import annotations

import contextlib
from dataclasses import dataclass

import torch

from storage.catalog import Catalog
from trainer.model import ModelConfig
from trainer.targets import Tonemap
from trainer.training.ema import WeightAverage
from trainer.training.losses import RendererLoss
from trainer.training.schedule import Knee


@dataclass(frozen=True)
class Rank:
    """Where this process trains: its rank among ``world``, its device, whether under DDP,
    and the dtype its steps autocast to (None: fp32; ``trainer.precision``)."""

    rank: int
    world: int
    device: torch.device
    distributed: bool
    autocast: torch.dtype | None = None

    @property
    def master(self) -> bool:
        return self.rank == 0

    @property
    def cuda(self) -> bool:
        return self.device.type == "cuda"

    @property
    def fmt(self) -> torch.memory_format:
        """The memory format of the network's weights and inputs: channels_last on every
        device (on the CPU, oneDNN's convolutions and GroupNorm run faster in it than in
        NCHW: ``benchmarks.cpu_train``)."""
        return torch.channels_last

    @property
    def precision(self) -> str:
        """``bf16`` or ``fp32``, as the run's log names it."""
        return "fp32" if self.autocast is None else "bf16"

    def autocasting(self):
        """The context a training step's forward pass runs in."""
        if self.autocast is None:
            return contextlib.nullcontext()
        return torch.autocast(self.device.type, dtype=self.autocast)


@dataclass
class Trainee:
    """The network being trained and everything a checkpoint holds, with the run's position:
    ``step`` (global), ``epoch``, and ``position`` (samples of the epoch already taken)."""

    model: torch.nn.Module  # trainer.model.NeuralRenderer, or trainer.zf's baseline
    net: torch.nn.Module  # the model, or DDP around it
    opt: torch.optim.Optimizer
    criterion: RendererLoss
    model_cfg: ModelConfig
    tonemap: Tonemap
    catalog: Catalog
    bad: torch.Tensor  # () bool: a non-finite gradient norm was seen (checked lazily)
    screen_uv: bytes | None = None  # the stores' layout, so checkpoints map new materials
    run_steps: int = 0  # the run's length in global steps, for the learning-rate schedule
    knee: Knee = (0, 1.0)  # where the cosine rate starts: trainer.training.schedule
    best: dict | None = None  # the best held-out score at a checkpoint: {"step", "psnr"}
    ema: WeightAverage | None = None  # rank 0's moving average of the weights (--ema-decay)
    step: int = 0
    epoch: int = 0
    position: int = 0
    deadline: float | None = None  # the time.monotonic() at which --time-limit stops the run
    timed_out: bool = False  # --time-limit stopped the run

    @property
    def rendering(self) -> torch.nn.Module:
        """The network the checkpoints render with: the moving average, else the model."""
        return self.model if self.ema is None else self.ema.model
