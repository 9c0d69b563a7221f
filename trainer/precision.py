"""In what precision a training step runs (``--precision``), as a plain function of the
setting and the device. torch is imported where it is used, so the CLI's options (which
list :data:`PRECISIONS`) load without it.

The weights, the optimizer and the losses that need it (MS-SSIM, FLIP) stay fp32 in every
case; bf16 autocast runs the convolutions in bf16, where the device multiplies bf16 in
hardware: CUDA, and a CPU with Intel AMX tiles, whose oneDNN bf16 convolutions train the
networks here about twice as fast as fp32 (``python -m benchmarks.cpu_train``). Elsewhere
bf16 is emulated and slower, so ``auto`` keeps fp32 there.
"""

from __future__ import annotations

#: ``auto``: bf16 where the device has bf16 arithmetic, else fp32
PRECISIONS = ("auto", "bf16", "fp32")


def cpu_has_bf16_units() -> bool:
    """Whether this CPU multiplies bf16 matrices in hardware (AMX tiles). ``torch.cpu``'s
    probe is private, so a torch without it reads as no."""
    import torch

    probe = getattr(torch.cpu, "_is_amx_tile_supported", None)
    return bool(probe and probe())


def autocast_dtype(precision: str, device_type: str, bf16_units: bool | None = None):
    """The dtype a training step on ``device_type`` (``cuda``, ``cpu``) autocasts to, None
    for fp32 throughout; ``bf16_units``: whether the CPU has them (None: ask this one)."""
    import torch

    if precision not in PRECISIONS:
        raise ValueError(f"--precision must be one of {', '.join(PRECISIONS)}, not {precision!r}")
    if precision == "fp32":
        return None
    if precision == "bf16" or device_type == "cuda":
        return torch.bfloat16
    units = cpu_has_bf16_units() if bf16_units is None else bf16_units
    return torch.bfloat16 if units else None
