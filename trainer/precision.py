"""In what precision a training step runs (``--precision``), as a plain function of the
setting and the device. torch is imported where it is used, so the CLI's options (which
list :data:`PRECISIONS`) load without it.

The weights, the optimizer and the losses that need it (MS-SSIM, FLIP) stay fp32 in every
case; bf16 autocast runs the convolutions in bf16, where the device multiplies bf16 in
hardware: CUDA, and a CPU with Intel AMX tiles or with AVX512-BF16's dot products (Intel
since Cooper Lake, AMD since Zen 4), whose oneDNN bf16 convolutions train the networks here
faster than fp32: about 2x with AMX, 1.2-1.6x with AVX512-BF16 (``python -m
benchmarks.cpu_train``). Elsewhere bf16 is emulated and slower, so ``auto`` keeps fp32
there.
"""

from __future__ import annotations

#: ``auto``: bf16 where the device has bf16 arithmetic, else fp32
PRECISIONS = ("auto", "bf16", "fp32")


#: ``torch.cpu``'s probes of the bf16 units: AMX tiles, AVX512-BF16
BF16_PROBES = ("_is_amx_tile_supported", "_is_avx512_bf16_supported")


def cpu_has_bf16_units() -> bool:
    """Whether this CPU multiplies bf16 in hardware (AMX tiles or AVX512-BF16). ``torch.cpu``'s
    probes are private, so a torch without them reads as no."""
    import torch

    probes = [getattr(torch.cpu, name, None) for name in BF16_PROBES]
    return any(bool(probe and probe()) for probe in probes)


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
