"""Where the network runs: ``--device auto|cuda|cpu`` as a torch device, refused in one line
where it cannot be had."""

from __future__ import annotations

import torch

from shaderball.errors import UserError


class NoCuda(UserError, ValueError):
    """``--device cuda`` where torch sees no CUDA device."""

    def __init__(self):
        super().__init__(f"--device cuda: this torch ({torch.__version__}) sees no CUDA device")


def pick_device(name: str = "auto") -> torch.device:
    """``auto``: CUDA when torch sees a device, else the CPU; ``cuda`` raises :class:`NoCuda`
    when it sees none."""
    if name == "auto":
        name = "cuda" if torch.cuda.is_available() else "cpu"
    if name == "cuda" and not torch.cuda.is_available():
        raise NoCuda()
    return torch.device(name)
