"""Where inference time goes: CUDA kernel time per operator of the network at 400².

    python -m benchmarks.infer_profile [--batch 128] [--compile]

Runs the BatchNorm-folded bf16 channels_last network (the ``benchmarks.infer`` fast path)
under ``torch.profiler`` and prints the CUDA kernels by total time a forward (with their share
and calls a forward), then every convolution layer's time and achieved TFLOP/s. Fresh
weights; speed does not depend on them. CUDA only.
"""

from __future__ import annotations

import argparse

import torch
from torch.autograd import DeviceType
from torch.profiler import ProfilerActivity, profile

from trainer.model import ModelConfig, NeuralRenderer
from trainer.rendering.infer import fast_network

#: the profiler's names of the operators that run one convolution each
CONVOLUTIONS = ("aten::convolution", "aten::cudnn_convolution_relu")


def conv_key(event) -> str:
    """A convolution's profiler event as ``[input shape], [weight shape], stride S``: two
    layers of the rewrite have the same shapes and differ in stride (an encoder convolution
    and a decoder level's sub-pixel one), so the shapes alone would mix them up."""
    args = event.concrete_inputs or []  # every convolution op here takes its stride 4th
    stride = args[3] if len(args) > 3 else "?"
    stride = stride[0] if isinstance(stride, (list, tuple)) else stride
    return f"{event.input_shapes[0]}, {event.input_shapes[1]}, stride {stride}"


def conv_flops(net: torch.nn.Module, x: torch.Tensor, light: torch.Tensor) -> dict:
    """``{conv_key: FLOPs}`` of the convolutions of one eager forward, as the profiler counts
    them (every ``aten::conv2d``, the sub-pixel rewrite's too)."""
    with profile(activities=[ProfilerActivity.CPU], with_flops=True, record_shapes=True) as p:
        net(x, light)
    flops = {}
    for e in p.events():
        if e.name == "aten::conv2d":
            flops[conv_key(e)] = flops.get(conv_key(e), 0.0) + float(e.flops)
    return flops


#: the ``--subpixel`` flags, each a keyword of :func:`trainer.rendering.infer.fast_network`
FAST_FLAGS = ("align", "edge_ring", "conv_relu", "light_sums", "fold_ring")


def parser() -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--batch", type=int, default=128)
    ap.add_argument("--compile", action="store_true", help="profile torch.compile instead")
    ap.add_argument("--rows", type=int, default=25)
    ap.add_argument("--subpixel", action="store_true", help="the trainer.rendering.fastnet rewrite")
    ap.add_argument("--align", type=int, default=8, help="with --subpixel: channels padded to x N")
    ap.add_argument(
        "--edge-ring",
        action="store_true",
        help="with --subpixel: phases on zero-padded inputs, rings as edge corrections two deep",
    )
    ap.add_argument(
        "--conv-relu", action="store_true", help="with --subpixel: conv + ReLU in one cuDNN call"
    )
    ap.add_argument(
        "--light-sums", action="store_true", help="with --subpixel: the light MLP as sums"
    )
    ap.add_argument(
        "--fold-ring",
        action="store_true",
        help="with --edge-ring: each ring's correction as one product",
    )
    return ap


def fast_kwargs(args: argparse.Namespace) -> dict:
    """The keywords of :func:`trainer.rendering.infer.fast_network` that ``args`` ask for."""
    return {"subpixel": args.subpixel} | {k: getattr(args, k) for k in FAST_FLAGS}


def profiled(net, x: torch.Tensor, light: torch.Tensor, forwards: int = 3):
    """The profiler's record of ``forwards`` forwards of ``net``, after five to warm it."""
    with torch.inference_mode():
        for _ in range(5):
            net(x, light)
        torch.cuda.synchronize()
        activities = [ProfilerActivity.CPU, ProfilerActivity.CUDA]
        with profile(activities=activities, record_shapes=True) as prof:
            for _ in range(forwards):
                net(x, light)
            torch.cuda.synchronize()
    return prof


def print_kernels(prof, batch: int, rows: int, forwards: int = 3) -> None:
    """The CUDA kernels by their time a forward, with their share and calls a forward."""
    kernels = [  # kernels only: not the span of a compiled graph's call ("## Call ... ##")
        r
        for r in prof.key_averages()
        if r.device_type == DeviceType.CUDA and not r.key.startswith("##")
    ]
    kernels.sort(key=lambda r: r.self_device_time_total, reverse=True)
    total = sum(r.self_device_time_total for r in kernels) / forwards / 1e3
    print(f"\nbatch {batch}: {total:.3f} ms of kernels a forward")
    print(f"{'kernel':<80}{'ms':>8}{'share':>7}{'calls':>6}")
    for r in kernels[:rows]:
        ms = r.self_device_time_total / forwards / 1e3
        if ms > 0:
            print(f"{r.key[:79]:<80}{ms:>8.3f}{ms / total:>7.1%}{r.count // forwards:>6}")


def conv_times(prof, forwards: int = 3) -> dict:
    """``{conv_key: ms of kernels a forward}`` of the profiled convolutions."""
    times = {}
    for e in prof.events():
        if e.name in CONVOLUTIONS:
            times[conv_key(e)] = times.get(conv_key(e), 0.0) + e.device_time_total / forwards / 1e3
    return times


def print_convolutions(prof, flops: dict, forwards: int = 3) -> None:
    """Every convolution layer's time a forward and achieved TFLOP/s."""
    print(f"\n{'convolution (input, weight, stride)':<66}{'ms':>8}{'TFLOP/s':>9}")
    shown = 0
    for key, ms in conv_times(prof, forwards).items():
        if key in flops and ms > 0:
            print(f"{key:<66}{ms:>8.3f}{flops[key] / ms / 1e9:>9.0f}")
            shown += 1
    if not shown:
        print("(none through aten::convolution: compiled into Triton templates, see above)")


def main() -> None:
    ap = parser()
    args = ap.parse_args()
    for flag, asked in (("--conv-relu", args.conv_relu), ("--light-sums", args.light_sums)):
        if asked and not args.subpixel:
            ap.error(f"{flag} is a form of the --subpixel rewrite")
    torch.backends.cudnn.benchmark = True
    cfg = ModelConfig(resolution=400)
    model = NeuralRenderer(cfg).cuda()
    fast = fast_kwargs(args)
    net = fast_network(model, compile=args.compile, **fast)
    # the same convolutions, each through aten::conv2d, whose FLOPs the profiler counts
    plain = fast_network(model, **(fast | {"conv_relu": False}))
    width = getattr(plain, "in_channels", cfg.in_channels)  # aligned: fed padded, as graphed
    x = torch.rand(args.batch, width, 400, 400, device="cuda", dtype=torch.bfloat16)
    x = x.contiguous(memory_format=torch.channels_last)
    light = torch.rand(args.batch, 4, device="cuda", dtype=torch.bfloat16)
    with torch.inference_mode():
        flops = conv_flops(plain, x, light)
    prof = profiled(net, x, light)
    print_kernels(prof, args.batch, args.rows)
    print_convolutions(prof, flops)


if __name__ == "__main__":
    main()
