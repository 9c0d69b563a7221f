"""A 3x3 convolution with its bias and ReLU as one operator that Inductor compiles around.

On CUDA it is one cuDNN call, ``torch.cudnn_convolution_relu`` (a fused convolution + bias +
ReLU graph), so the output is written once, already rectified. Left to Inductor, a
convolution whose consumer is another convolution (the encoder's, whose outputs feed the
next level and a skip) is written by cuDNN and then read and written again by a ReLU pass
(``benchmarks.infer --conv-relu`` times the difference).

Why a custom operator: ``torch.cudnn_convolution_relu`` has no meta kernel, so Dynamo cannot
trace it; :func:`conv_relu` is registered with ``torch.library.custom_op`` and a fake
implementation that gives the output's shape and memory format, and Inductor calls it as an
extern kernel. Elsewhere (CPU) it is ``relu(conv2d(...))``, the same numbers.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch._prims_common import suggest_memory_format


def _out_shape(x: torch.Tensor, weight: torch.Tensor, stride: int) -> tuple[int, ...]:
    n, _, h, w = x.shape
    return n, weight.shape[0], (h - 1) // stride + 1, (w - 1) // stride + 1


@torch.library.custom_op("shaderball::conv_relu", mutates_args=())
def conv_relu(
    x: torch.Tensor, weight: torch.Tensor, bias: torch.Tensor | None, stride: int
) -> torch.Tensor:
    """``relu(conv2d(x, weight, bias, stride, padding=1))`` for a 3x3 ``weight``, in the
    memory format of ``x``."""
    if x.is_cuda:
        pair = (stride, stride)
        y = torch.cudnn_convolution_relu(x, weight, bias, pair, (1, 1), (1, 1), 1)
    else:
        y = F.relu(F.conv2d(x, weight, bias, stride, 1))
    return y.contiguous(memory_format=suggest_memory_format(x))


@conv_relu.register_fake
def _(x: torch.Tensor, weight: torch.Tensor, bias: torch.Tensor | None, stride: int):
    shape = _out_shape(x, weight, stride)
    return x.new_empty(shape).contiguous(memory_format=suggest_memory_format(x))
