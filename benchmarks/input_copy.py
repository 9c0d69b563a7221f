"""The copy of a batch into a CUDA graph's input: ``copy_`` against an Inductor-compiled copy.

    python3 -m benchmarks.input_copy [--batch 128] [--resolution 400] [--iters 30]

``trainer.rendering.infer.GraphedRenderer`` copies each fp32 NCHW batch of maps into its bf16
channels_last input (the first 10 of 16 channels) before the replay: at batch 128 and 400²
it reads 0.82 GB and writes 0.41 GB, a share of the batched frames' time worth measuring.
This times that copy as the renderer does it (``Tensor.copy_``)
and the same copy compiled by Inductor (one tiled kernel that transposes as it converts),
checks that both write the same values, and prints ms and GB/s of each. On CPU it runs too
(smaller sizes make it quick), but the question is the GPU's.
"""

from __future__ import annotations

import argparse

import torch

from benchmarks.infer import timed
from trainer.model import ModelConfig
from trainer.rendering.fastnet import round_up
from trainer.rendering.infer import pick_device

#: the maps' channels and the graph input's, aligned as ``fast_network`` aligns them
CHANNELS = ModelConfig().in_channels
WIDTH = round_up(CHANNELS, 8)


def copy_in(dst: torch.Tensor, src: torch.Tensor) -> None:
    """What ``GraphedRenderer.__call__`` does with a batch of maps."""
    dst[:, : src.shape[1]].copy_(src)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--batch", type=int, default=128)
    ap.add_argument("--resolution", type=int, default=400)
    ap.add_argument("--iters", type=int, default=30)
    ap.add_argument("--device", default="auto", choices=["auto", "cuda", "cpu"])
    args = ap.parse_args()
    if args.batch < 1 or args.resolution < 1 or args.iters < 1:
        ap.error("--batch, --resolution and --iters must be positive")
    device = pick_device(args.device)
    n, r = args.batch, args.resolution
    src = torch.rand(n, CHANNELS, r, r, device=device)
    dst = torch.zeros(n, WIDTH, r, r, device=device, dtype=torch.bfloat16)
    dst = dst.contiguous(memory_format=torch.channels_last)
    compiled = torch.compile(copy_in, dynamic=False)
    compiled(dst, src)  # compiled and checked before it is timed
    want = src.to(torch.bfloat16)
    if not torch.equal(dst[:, :CHANNELS], want):
        raise SystemExit("the compiled copy wrote other values than copy_")
    moved = src.numel() * (src.element_size() + dst.element_size())
    cuda = device.type == "cuda"
    print(f"device: {device}; batch {n}, {r}², {moved / 1e9:.3g} GB moved a copy")
    for name, fn in (("copy_", copy_in), ("Inductor-compiled", compiled)):
        s = timed(lambda fn=fn: fn(dst, src), args.iters, cuda)
        # general formats: a tiny copy on a loaded machine must not print as 0
        print(f"{name:<20}{s * 1e3:>10.4g} ms{moved / s / 1e9:>10.4g} GB/s", flush=True)


if __name__ == "__main__":
    main()
