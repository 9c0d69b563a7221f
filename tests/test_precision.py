"""``--precision``: what a training step autocasts to, as a plain function of the setting,
the device and whether the CPU has bf16 matrix units."""

import pytest
import torch

from trainer.precision import BF16_PROBES, PRECISIONS, autocast_dtype, cpu_has_bf16_units
from trainer.training.config import TrainConfig


@pytest.mark.parametrize(
    ("precision", "device", "units", "dtype"),
    [
        ("auto", "cuda", False, torch.bfloat16),
        ("auto", "cpu", True, torch.bfloat16),
        ("auto", "cpu", False, None),  # emulated bf16 is slower than fp32
        ("bf16", "cpu", False, torch.bfloat16),  # asked for: given, slow or not
        ("fp32", "cuda", True, None),
        ("fp32", "cpu", True, None),
    ],
)
def test_auto_trains_in_bf16_only_where_the_device_multiplies_it(precision, device, units, dtype):
    assert autocast_dtype(precision, device, bf16_units=units) is dtype


def test_this_cpu_is_asked_when_nothing_says_and_a_bad_precision_is_refused_in_one_line():
    assert all(hasattr(torch.cpu, probe) for probe in BF16_PROBES)  # torch still has them
    assert isinstance(cpu_has_bf16_units(), bool)
    mine = torch.bfloat16 if cpu_has_bf16_units() else None
    assert autocast_dtype("auto", "cpu") is mine
    with pytest.raises(
        ValueError, match=r"^--precision must be one of auto, bf16, fp32, not 'fp16'$"
    ):
        autocast_dtype("fp16", "cpu")
    assert TrainConfig(store=("s",)).precision == "auto" and PRECISIONS[0] == "auto"
    with pytest.raises(
        ValueError, match=r"^--precision must be one of auto, bf16, fp32, not 'fp16'$"
    ):
        TrainConfig(store=("s",), precision="fp16")  # refused as the run's config is made
