"""Inference benchmark at 400² (or ``--resolution``): ms per frame at batch 1, frames/s batched.

    .venv/bin/python -m benchmarks.infer [--batch 8] [--iters 20] [--device auto] [--compile]
        [--align N] [--zero-edge-ring] [--conv-relu] [--light-sums] [--fold-ring]
        [--resolution 400] [--only TEXT]... [--rounds K]

Rows: eager fp32, the same with BatchNorm folded in channels_last, and the exact fp32
rewrite (``trainer.rendering.fastnet``: BatchNorm folded, sub-pixel convolutions, channels_last) on
every device (``trainer.rendering.infer.Renderer`` runs one of the last two on CPU, by resolution:
``trainer.rendering.infer.CPU_SUBPIXEL_FROM``); on CPU, where onnxruntime is installed, the folded
network exported as ``trainer export`` exports it, run by ONNX Runtime; on CUDA also bf16 +
channels_last eager (cudnn.benchmark), the same with BatchNorm folded, that with the weights
cast to bf16 once and replayed as a CUDA graph (``trainer.rendering.infer.GraphedRenderer``), the
rewrite so replayed, and with ``--compile`` both after torch.compile (Inductor
``max-autotune-no-cudagraphs``: fused pointwise work around the tuned convolutions, then
captured). Every rewrite row pads its channel counts to multiples of ``--align`` (8, the fast
path's default: ``trainer.rendering.infer.fast_network``) with zero-weight channels;
``--align 1`` keeps the model's own counts. ``--zero-edge-ring`` adds the compiled rewrite
with the sub-pixel convolutions on zero-padded inputs and the rings as corrections two deep
from the edges of each level's input (``trainer.rendering.fastnet.zero_edges``).
``--conv-relu`` adds the compiled rewrite (with the zero-padded edge ring when that is asked
for) whose encoder convolutions run with their ReLU in one cuDNN call
(``trainer.rendering.convrelu``). ``--light-sums`` adds the zero-padded edge ring with conv +
ReLU (``trainer.rendering.infer.EDGE_RELU``) with the light encoder's layers as sums
(``trainer.rendering.fastnet.SummedMLP``); ``--fold-ring`` that form (with ``--light-sums``,
with its sums) with each ring's correction as one product
(``trainer.rendering.fastnet.zero_edges_folded``: ``trainer.rendering.infer.FASTEST``).
``benchmarks.infer_profile`` shows where the time goes, kernel by kernel.
The network is the paper's (width 64, skips) with fresh weights (speed does not depend on
them); inputs are real maps and suns from the benchmark store (``benchmarks.trainstore``).
At another ``--resolution`` the store's 400² maps are resized to it (nearest: speed does not
depend on the values).
Times are medians over ``--iters`` after warm-up, each synchronised on CUDA; ``max |diff|`` is
the largest difference of each mode's batch-1 image from eager fp32 (display units, [0, 1]);
``build s`` the seconds a CUDA-graph row took to compile, autotune and capture at both batch
sizes (what a device call spends before timing it). ``frames/s`` includes copying the fp32
NCHW batch into a graph row's bf16 channels_last input; ``in place`` is the same graph's
replay alone (``GraphedRenderer.replay``), for a producer that writes its frames there.
``--rounds K`` then times every row again, K rounds of every row in turn, and prints each
row's medians and its batch-1 time over the first row's: rows built and timed minutes apart
meet different machine states.
"""

from __future__ import annotations

import argparse
import copy
import importlib.util
import statistics
import sys
import tempfile
import time

import torch
import torch.nn.functional as F

from benchmarks.results import Table, save
from benchmarks.train import device_name
from benchmarks.trainstore import DEFAULT, ensure_store
from trainer.model import ModelConfig, NeuralRenderer, fold_batchnorm
from trainer.rendering.export import save_onnx
from trainer.rendering.fastnet import SubpixelRenderer
from trainer.rendering.infer import EDGE_RELU, GraphedRenderer, pick_device
from trainer.samples import SampleReader
from trainer.targets import model_inputs
from trainer.training.data import Catalog


def timed(fn, iters: int, cuda: bool) -> float:
    """Median seconds of ``fn()`` over ``iters`` runs (after 3 warm-up runs)."""
    times = []
    for i in range(iters + 3):
        if cuda:
            torch.cuda.synchronize()
        t0 = time.perf_counter()
        fn()
        if cuda:
            torch.cuda.synchronize()
        if i >= 3:
            times.append(time.perf_counter() - t0)
    return statistics.median(times)


def interleaved(rows, rounds: int, clock) -> dict[str, list[float]]:
    """``{name: seconds, one a round}`` of ``rows`` (``(name, fn)``), timed by ``clock(fn)``
    one after the other, round after round: a drift of the machine over the run (clocks, heat,
    a neighbour's load) falls on every row alike, so ratios between rows hold where rows timed
    once each, minutes apart, can differ by more than the effect measured."""
    times = {name: [] for name, _ in rows}
    for _ in range(rounds):
        for name, fn in rows:
            times[name].append(clock(fn))
    return times


def graphed(model, batch: int, fast: dict) -> GraphedRenderer:
    """A row's CUDA graph: ``fast`` are :func:`trainer.rendering.infer.fast_network`'s
    keywords."""
    return GraphedRenderer(model, batch, **fast)


def built(name: str, build):
    """``build()``, or ``None`` when it raises, said in one line on stderr: a form that this
    machine's torch or cuDNN cannot run costs its own row, not the rows after it."""
    try:
        return build()
    except Exception as exc:  # any failure to build: reported, and the run goes on
        why = (str(exc).strip().splitlines() or [""])[0][:300]
        print(f"{name}: not built: {type(exc).__name__}: {why}", file=sys.stderr)
        return None


def rounds_table(one: dict[str, list[float]], many: dict[str, list[float]], batch: int) -> str:
    """The ``--rounds`` table: per row the median ms a frame at batch 1, its range over the
    rounds, the median frames/s batched, and the batch-1 median over the first row's."""
    first = statistics.median(next(iter(one.values())))
    lines = [f"{'mode':<32}{'ms/frame (b=1)':>16}{'range':>16}{'frames/s':>12}{'b=1 ratio':>11}"]
    for name, t in one.items():
        med, span = statistics.median(t), f"{min(t) * 1e3:.3f}-{max(t) * 1e3:.3f}"
        rate = batch / statistics.median(many[name])
        lines.append(f"{name:<32}{med * 1e3:>16.3f}{span:>16}{rate:>12.1f}{med / first:>11.3f}")
    return "\n".join(lines)


def parser() -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--store", default=DEFAULT)
    ap.add_argument("--batch", type=int, default=8)
    ap.add_argument("--iters", type=int, default=20)
    ap.add_argument(
        "--rounds",
        type=int,
        default=1,
        metavar="K",
        help="after the rows, time them again K times in turn and print medians and ratios "
        "(ratios that a drift of the machine does not bias); every row's network and CUDA "
        "graphs stay in memory to the end, so pick a few rows with --only",
    )
    ap.add_argument("--device", default="auto", choices=["auto", "cuda", "cpu"])
    ap.add_argument("--resolution", type=int, default=400, help="a multiple of 16 (default 400)")
    ap.add_argument(
        "--compile",
        action="store_true",
        help="add a torch.compile + CUDA graph row (CUDA; minutes of autotuning)",
    )
    ap.add_argument(
        "--align",
        type=int,
        default=8,
        metavar="N",
        help="pad the subpixel rows' channel counts to multiples of N (default 8, for tensor "
        "cores; 1: the model's own)",
    )
    ap.add_argument(
        "--zero-edge-ring",
        action="store_true",
        help="add a compiled subpixel row whose sub-pixel convolutions read zero-padded "
        "inputs, with rings as two-deep corrections from the edges (trainer.rendering.fastnet."
        "zero_edges; CUDA)",
    )
    ap.add_argument(
        "--conv-relu",
        action="store_true",
        help="add a compiled subpixel row (with --zero-edge-ring: of that form) whose encoder "
        "convolutions run with their ReLU in one cuDNN call (trainer.rendering.convrelu; CUDA)",
    )
    ap.add_argument(
        "--light-sums",
        action="store_true",
        help="add the zero-padded edge ring with conv + ReLU (trainer.rendering.infer.EDGE_RELU) "
        "with the light encoder's layers as sums, one kernel each "
        "(trainer.rendering.fastnet.SummedMLP; CUDA)",
    )
    ap.add_argument(
        "--fold-ring",
        action="store_true",
        help="add the zero-padded edge ring with conv + ReLU (with --light-sums: with its "
        "light sums) with each ring's correction as one batched product "
        "(trainer.rendering.fastnet.zero_edges_folded; CUDA)",
    )
    ap.add_argument(
        "--only",
        action="append",
        default=[],
        metavar="TEXT",
        help="run only the rows whose name contains TEXT; given again, the rows that contain "
        "any of them (eager fp32 stays the reference)",
    )
    return ap


def graph_rows(args: argparse.Namespace) -> list[tuple[str, dict]]:
    """The CUDA-graph rows that ``args`` ask for, in order: ``(name, keyword arguments of
    trainer.rendering.infer.GraphedRenderer)``. The rewrite's rows take ``--align``'s channels
    (named when not the default 8) and are compiled unless told."""
    x1 = f", channels x{args.align}" if args.align != 8 else ""

    def rewrite(name: str, **fast) -> tuple[str, dict]:
        return name + x1, {"compile": True, "subpixel": True, "align": args.align, **fast}

    rows = [
        ("  + bf16 weights, CUDA graph", {}),
        rewrite("subpixel bf16, CUDA graph", compile=False),
    ]
    if args.compile:
        rows += [
            ("torch.compile + CUDA graph", {"compile": True}),
            rewrite("subpixel compiled + graph"),
        ]
    if args.zero_edge_ring:
        rows.append(rewrite("subpixel compiled, zero-padded edge ring", edge_ring=True))
    if args.conv_relu:
        zero = args.zero_edge_ring
        name = f"subpixel compiled{', zero-padded edge ring' * zero}, conv+ReLU"
        rows.append(rewrite(name, edge_ring=zero, conv_relu=True))
    edge_relu = (
        "subpixel compiled, zero-padded edge ring, conv+ReLU"  # trainer.rendering.infer.EDGE_RELU
    )
    if args.light_sums:
        rows.append(rewrite(f"{edge_relu}, light sums", **(EDGE_RELU | {"light_sums": True})))
    if args.fold_ring:  # with --light-sums, of that form
        sums = args.light_sums
        name = f"{edge_relu}{', light sums' * sums}, ring in one product"
        rows.append(rewrite(name, **(EDGE_RELU | {"light_sums": sums, "fold_ring": True})))
    return rows


class Bench:
    """The inputs, the model, the eager fp32 reference image and the rows timed so far."""

    def __init__(self, args: argparse.Namespace):
        self.args = args
        self.device = pick_device(args.device)
        self.cuda = self.device.type == "cuda"
        split = Catalog.snapshot([ensure_store(args.store)], 0, 0.0, None).split("train")
        data = SampleReader(split).batch(list(range(min(args.batch, len(split)))))
        reps = -(-args.batch // len(data["id"]))
        x_all = model_inputs(data["maps"]).repeat(reps, 1, 1, 1)[: args.batch]
        x_all = F.interpolate(x_all, size=args.resolution, mode="nearest")
        self.x_all = x_all.to(self.device)
        self.l_all = data["light"].repeat(reps, 1)[: args.batch].to(self.device)
        self.model = NeuralRenderer(ModelConfig(resolution=args.resolution)).to(self.device)
        self.model.eval()
        with torch.inference_mode():
            self.reference = self.model(self.x_all[:1], self.l_all[:1]).float()
        self.measured = []  # (name, batch-1 call, batched call) of each row, for --rounds

    def header(self) -> None:
        r, batch = self.args.resolution, self.args.batch
        print(f"device: {device_name(self.args.device)}; {r}², batch {batch} for frames/s")
        self.table = Table(
            title=f"Inference (`make bench-infer`): {r}², batch {batch} for frames/s",
            columns=["mode", "ms/frame (b=1)", "frames/s", "in place", "max |diff|", "build s"],
            machine=device_name(self.args.device),
        )
        head = f"{'mode':<32}{'ms/frame (b=1)':>16}{'frames/s':>12}{'in place':>10}"
        print(head + f"{'max |diff|':>12}{'build s':>9}", flush=True)

    def report(self, name, one, many, err, build=None, replay=None) -> None:
        """One row, printed as soon as it is measured (compiled rows take minutes each);
        ``build``: the seconds a graph row took to compile, tune and capture; ``replay``: a
        graph row's batched seconds with its input already in the graph's buffer."""
        batch = self.args.batch
        built_s = "-" if build is None else f"{build:.0f}"
        alone = "-" if replay is None else f"{batch / replay:.1f}"
        row = f"{name:<32}{one * 1e3:>16.3f}{batch / many:>12.1f}{alone:>10}"
        print(row + f"{err:>12.4f}{built_s:>9}", flush=True)
        self.table.rows.append(
            [name, round(one * 1e3, 3), round(batch / many, 1), alone, round(err, 4), built_s]
        )

    def measure(self, name, one, many) -> tuple[float, float]:
        """Seconds of ``one()`` and ``many()``; with ``--rounds``, the row is kept (and with it
        its network and CUDA graphs) to be timed again at the end."""
        if self.args.rounds > 1:
            self.measured.append((name, one, many))
        return self.timed(one), self.timed(many)

    def timed(self, fn) -> float:
        return timed(fn, self.args.iters, self.cuda)

    def error(self, out: torch.Tensor) -> float:
        """Largest difference from the eager fp32 image, in [0, 1] display units."""
        return (out.float() - self.reference).abs().max().item()

    def wanted(self, name: str) -> bool:
        return not self.args.only or any(text in name for text in self.args.only)

    def eager_row(self, name, net, bf16, fmt) -> None:
        if not self.wanted(name):
            return
        net.to(memory_format=fmt)
        x1, xb = (
            self.x_all[:1].contiguous(memory_format=fmt),
            self.x_all.contiguous(memory_format=fmt),
        )
        l1, lb = self.l_all[:1], self.l_all

        def run(x, light):
            with (
                torch.inference_mode(),
                torch.autocast(self.device.type, torch.bfloat16, enabled=bf16),
            ):
                return net(x, light)

        one, many = self.measure(name, lambda: run(x1, l1), lambda: run(xb, lb))
        self.report(name, one, many, self.error(run(x1, l1)))

    def graph_row(self, name, **fast) -> None:
        if not self.wanted(name):
            return
        start = time.perf_counter()
        if (g1 := built(name, lambda: graphed(self.model, 1, fast))) is None:
            return
        # on stderr, so that a run stopped while building says how far it got
        print(f"{name}: batch 1 built in {time.perf_counter() - start:.0f} s", file=sys.stderr)
        batch = self.args.batch
        if (gb := built(name, lambda: graphed(self.model, batch, fast))) is None:
            return
        build = time.perf_counter() - start
        x1, l1, xb, lb = self.x_all[:1], self.l_all[:1], self.x_all, self.l_all
        one, many = self.measure(name, lambda: g1(x1, l1), lambda: gb(xb, lb))
        replay = self.timed(gb.replay)  # the input copied in by the line above
        self.report(name, one, many, self.error(g1(x1, l1)), build, replay)

    def onnx_row(self, name, net) -> None:
        """The folded network exported (``trainer.rendering.export.save_onnx``) and run by ONNX
        Runtime's CPU provider, on numpy copies of the same inputs."""
        if not self.wanted(name) or self.cuda or importlib.util.find_spec("onnxruntime") is None:
            return
        import onnxruntime as ort

        with tempfile.TemporaryDirectory() as tmp:
            path = f"{tmp}/net.onnx"
            save_onnx(net, {"x": self.x_all[:1], "light": self.l_all[:1]}, "image", path)
            session = ort.InferenceSession(path, providers=["CPUExecutionProvider"])

        def run(x, light):
            return session.run(["image"], {"x": x, "light": light})[0]

        x1, l1, xb, lb = (
            t.numpy() for t in (self.x_all[:1], self.l_all[:1], self.x_all, self.l_all)
        )
        one, many = self.measure(name, lambda: run(x1, l1), lambda: run(xb, lb))
        self.report(name, one, many, self.error(torch.from_numpy(run(x1, l1))))

    def rounds(self) -> None:
        """``--rounds``: every kept row timed again, round after round, and the medians."""
        if not self.measured:
            return
        rounds = self.args.rounds
        one = interleaved([(n, f) for n, f, _ in self.measured], rounds, self.timed)
        many = interleaved([(n, f) for n, _, f in self.measured], rounds, self.timed)
        print(f"\nthe rows again, {rounds} rounds in turn (medians):")
        print(rounds_table(one, many, self.args.batch), flush=True)
        self.table.notes.append(
            f"timed again, {rounds} rounds in turn (medians, ms/frame at batch 1 and frames/s): "
            + "; ".join(
                f"{n} {statistics.median(one[n]) * 1e3:.3f} ms, "
                f"{self.args.batch / statistics.median(many[n]):.1f}/s"
                for n in one
            )
        )


def main() -> None:
    ap = parser()
    args = ap.parse_args()
    if args.rounds < 1:
        ap.error(f"--rounds must be at least 1, not {args.rounds}")
    if args.resolution < 16 or args.resolution % 16:
        ap.error(f"--resolution {args.resolution} is not a positive multiple of 16")
    bench = Bench(args)
    bench.header()
    model = bench.model
    folded = fold_batchnorm(model)  # its own weights: the rewrite below copies them
    bench.eager_row("eager fp32", model, False, torch.contiguous_format)
    bench.eager_row("folded fp32 channels_last", folded, False, torch.channels_last)
    subpixel = SubpixelRenderer(folded)
    bench.eager_row("subpixel fp32 channels_last", subpixel, False, torch.channels_last)
    bench.onnx_row("ONNX Runtime fp32 (CPU)", folded.to(memory_format=torch.contiguous_format))
    if bench.cuda:
        torch.backends.cudnn.benchmark = True
        # a copy: each row keeps its own network, in its own format, for --rounds
        bench.eager_row("eager bf16 channels_last", copy.deepcopy(model), True, torch.channels_last)
        bench.eager_row("  + BatchNorm folded", folded, True, torch.channels_last)
        for name, fast in graph_rows(args):
            bench.graph_row(name, **fast)
    bench.rounds()
    save("infer-cuda" if bench.cuda else "infer-cpu", bench.table)


if __name__ == "__main__":
    main()
