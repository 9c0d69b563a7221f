"""The kernels Inductor plans for the compiled fast network, worked out on a CPU machine.

    .venv/bin/python -m benchmarks.kernel_plan [--subpixel] [--edge-ring [--fold-ring]]
        [--conv-relu] [--light-sums] [--batch 8] [--resolution 400] [--width 64] [--align 8]

Compiles ``trainer.rendering.infer.fast_network`` (bf16, channels_last) with Inductor's Triton
backend on the CPU and prints, in launch order, what the generated program calls: each
extern kernel (cuDNN convolutions, cuBLAS products on a GPU) and each fused Triton kernel
with the elements it covers; then the fused kernels' elements in all (a stand-in for the
pointwise passes' traffic). The plan is made before any kernel runs, so no GPU and no
working Triton CPU driver are needed: which pointwise work Inductor fuses, and which
intermediate tensors it writes out, can be checked here before a device call measures it.

Inductor's fusion choices change between torch versions. To see the plan a device will
run, run this with the device's torch (``gpu.sh`` prints it), for example in a separate
virtual environment: ``python3.11 -m venv /tmp/t && /tmp/t/bin/pip install torch==2.11.0
numpy zarr tenacity click``, then ``PYTHONPATH=. /tmp/t/bin/python -m
benchmarks.kernel_plan``. It compiles with ``fast_network``'s Inductor options
(``trainer.rendering.infer.compile_options``) but the autotuning, at the dtype and sizes of the
device's run; the choice of each convolution's algorithm is the device's (cuDNN, at run
time).
"""

from __future__ import annotations

import argparse
import re

import torch

from trainer.model import ModelConfig, NeuralRenderer
from trainer.rendering.infer import compile_options, fast_network

#: a kernel launch in Inductor's generated ``call``: a fused Triton kernel or an extern one
#: (one of Inductor's, or an operator it calls as it is, such as ``shaderball.conv_relu``)
LAUNCH = re.compile(
    r"^\s*(?:\w+ = )?(?:(triton_\w+)\.run\((.*)\)"
    r"|(?:extern_kernels|torch\.ops\.(?!aten\.)\w+)\.(\w+)(?:\.default)?\()"
)


def plan_source(
    net: torch.nn.Module, x: torch.Tensor, light: torch.Tensor, options: dict | None = None
) -> str:
    """The Python program Inductor generates for ``net(x, light)`` on the CPU with its
    Triton backend and ``options`` (Inductor's), captured before it is loaded (it could not
    run here)."""
    import torch._inductor.config as inductor_config
    import torch.utils._triton as triton_utils
    from torch._inductor import graph

    captured = []
    codegen = graph.GraphLowering.codegen

    def keep(self, *args, **kwargs):
        out = codegen(self, *args, **kwargs)
        captured.append(out[0] if isinstance(out, tuple) else out)
        return out

    hash_fn = triton_utils.triton_hash_with_backend
    torch._dynamo.reset()
    # the Triton kernels' cache key asks the (absent) GPU driver for its target
    triton_utils.triton_hash_with_backend = lambda: "kernel-plan"
    graph.GraphLowering.codegen = keep
    try:
        with inductor_config.patch(cpu_backend="triton", compile_threads=1):
            compiled = torch.compile(net, dynamic=False, options=options or {})
            try:
                with torch.no_grad():
                    compiled(x, light)
            except Exception:  # loading or running the program: it was captured before
                if not captured:
                    raise
    finally:
        graph.GraphLowering.codegen = codegen
        triton_utils.triton_hash_with_backend = hash_fn
        torch._dynamo.reset()
    source = captured[-1]
    return str(getattr(source, "value", source))


def launches(source: str) -> list[tuple[str, int]]:
    """``(kernel, elements)`` of each launch in the program's ``call``, in order; an extern
    kernel as ``extern <name>`` with 0 elements."""
    out = []
    for line in source[source.index("def call(") :].splitlines():
        m = LAUNCH.match(line)
        if m and m.group(1):
            sizes = [int(v) for v in re.findall(r"(?<![\w.])(\d+)(?=,)", m.group(2) + ",")]
            out.append((m.group(1), sizes[-1] * (sizes[-2] if len(sizes) > 1 else 1)))
        elif m:
            out.append((f"extern {m.group(3)}", 0))
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--resolution", type=int, default=400)
    ap.add_argument("--width", type=int, default=64)
    ap.add_argument("--batch", type=int, default=8)
    ap.add_argument("--subpixel", action="store_true", help="the trainer.rendering.fastnet rewrite")
    ap.add_argument(
        "--edge-ring",
        action="store_true",
        help="with --subpixel: zero-padded phases, rings as edge corrections two deep",
    )
    ap.add_argument(
        "--conv-relu", action="store_true", help="with --subpixel: conv + ReLU as one operator"
    )
    ap.add_argument(
        "--light-sums", action="store_true", help="with --subpixel: the light MLP as sums"
    )
    ap.add_argument(
        "--fold-ring", action="store_true", help="with --edge-ring: each ring as one product"
    )
    ap.add_argument("--align", type=int, default=8, metavar="N")
    args = ap.parse_args()
    if args.edge_ring and not args.subpixel:
        ap.error("--edge-ring is a form of the --subpixel rewrite")
    if args.fold_ring and not args.edge_ring:
        ap.error("--fold-ring is a form of --edge-ring")
    for flag, asked in (("--conv-relu", args.conv_relu), ("--light-sums", args.light_sums)):
        if asked and not args.subpixel:
            ap.error(f"{flag} is a form of the --subpixel rewrite")
    model = NeuralRenderer(ModelConfig(resolution=args.resolution, width=args.width)).eval()
    net = fast_network(
        model,
        subpixel=args.subpixel,
        align=args.align,
        edge_ring=args.edge_ring,
        conv_relu=args.conv_relu,
        light_sums=args.light_sums,
        fold_ring=args.fold_ring,
    )
    r = args.resolution
    channels = getattr(net, "in_channels", model.config.in_channels)
    x = torch.rand(args.batch, channels, r, r, dtype=torch.bfloat16)
    light = torch.rand(args.batch, 4, dtype=torch.bfloat16)
    # fast_network's options but the autotuning: the GPU chooses its algorithms itself
    options = compile_options()
    tuning = ("max_autotune", "coordinate_descent_tuning")
    options = {k: v for k, v in options.items() if k not in tuning}
    x = x.contiguous(memory_format=torch.channels_last)
    plan = launches(plan_source(net, x, light, options))
    print(f"torch {torch.__version__}; {r}², width {args.width}, batch {args.batch}")
    for i, (name, elements) in enumerate(plan):
        print(f"{i:>4}  {name[:100]:<100} {elements or '':>12}")
    fused = [e for n, e in plan if not n.startswith("extern")]
    print(
        f"{len(plan)} launches: {len(plan) - len(fused)} extern, {len(fused)} fused Triton "
        f"kernels covering {sum(fused) / 1e6:,.1f} M elements in all"
    )


if __name__ == "__main__":
    main()
