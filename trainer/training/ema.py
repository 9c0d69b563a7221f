"""An exponential moving average of the network's weights (``trainer train --ema-decay D``).

After every optimizer step the average moves towards the trained weights:
``average = d * average + (1 - d) * trained``, with ``d = min(D, (1 + n) / (10 + n))`` after
``n`` earlier updates (:func:`decay_at`, the warm-up of TensorFlow's
``ExponentialMovingAverage``), so that the first steps' weights, far from trained, fade fast.
BatchNorm's running statistics are averaged alike; its integer batch counter is copied.

The average is what a run's checkpoints render with (:func:`trainer.checkpoint.weights`) and
what its held-out scores and ``best.pt`` measure; the trained weights stay in the checkpoint
beside it, for resuming and for ``trainer eval --weights trained``.

Hand-written rather than ``torch.optim.swa_utils.AveragedModel``: its EMA has a fixed decay
(no warm-up by step) and blends integer buffers as floats; this is the one fused
``_foreach_lerp_`` it would run, with the decay computed on the host (no device sync).
"""

from __future__ import annotations

import copy

import torch


def decay_at(updates: int, decay: float) -> float:
    """The decay of the update after ``updates`` earlier ones, for a run's ``decay``."""
    return min(decay, (1 + updates) / (10 + updates))


class WeightAverage:
    """The moving average of a model's weights: a copy of the model in eval mode, no grads."""

    def __init__(self, model: torch.nn.Module, decay: float, updates: int = 0):
        if not 0 < decay < 1:
            raise ValueError(f"the average's decay must be in (0, 1), not {decay}")
        self.model = copy.deepcopy(model).eval().requires_grad_(False)
        self.decay = decay
        self.updates = updates

    def _pairs(self, model: torch.nn.Module):
        mine = self.model.state_dict(keep_vars=True)
        theirs = model.state_dict(keep_vars=True)
        return [(mine[k].detach(), theirs[k].detach()) for k in mine]

    @torch.no_grad()
    def update(self, model: torch.nn.Module) -> None:
        """Move the average towards ``model``'s weights (one call after each step)."""
        d = decay_at(self.updates, self.decay)
        pairs = self._pairs(model)
        floats = [(a, b) for a, b in pairs if a.is_floating_point()]
        if floats:
            torch._foreach_lerp_([a for a, _ in floats], [b for _, b in floats], 1 - d)
        for a, b in pairs:
            if not a.is_floating_point():
                a.copy_(b)
        self.updates += 1

    def state_dict(self) -> dict:
        """What a checkpoint keeps: ``{"weights", "decay", "updates"}``."""
        return {"weights": self.model.state_dict(), "decay": self.decay, "updates": self.updates}

    def load_state_dict(self, state: dict) -> None:
        self.model.load_state_dict(state["weights"])
        self.updates = state["updates"]
