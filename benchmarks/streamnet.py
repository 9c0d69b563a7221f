"""The network on two CUDA streams, for batch 1: the skip convolutions and the light MLP
run beside the critical path.

At batch 1 the deep levels' convolutions fill a few of the GPU's SMs each, one after the
other. A decoder convolution of ``cat(u, skip)`` splits into ``conv(u, W_u) + conv(skip,
W_skip)`` (:mod:`trainer.rendering.fastnet`), and the skip halves depend on the encoder alone. So a
side stream computes them, deepest first, and the light MLP (which depends on nothing) while
the main stream runs the bottleneck and the decoder's ``W_u`` halves, whose inputs have half
or two thirds of the concatenation's channels; the main stream waits for each skip result
just before adding it. The same numbers as :class:`trainer.rendering.fastnet.SubpixelRenderer` up to
rounding, in another order.

Inductor does not compile across streams, so the forward is cut into segments at the
stream switches and each is compiled alone (:meth:`StreamedRenderer.compile_segments`); the
switches are CUDA events in plain Python, which a CUDA graph captures as dependencies between
the two streams' kernels (:class:`trainer.rendering.infer.GraphedRenderer`). On CPU the segments run
in the same order on one stream, which is how the tests check the split.
"""

from __future__ import annotations

import contextlib

import torch
import torch.nn.functional as F
from torch import nn

from trainer.rendering.fastnet import Conv, PlainLevel, SubpixelLevel, SubpixelRenderer
from trainer.rendering.infer import fast_layers


class PlainUp(nn.Module):
    """``conv(up(z), weight, padding=1)``, no bias: the :class:`PlainLevel` form of a
    decoder level's ``W_u`` half."""

    def __init__(self, weight: torch.Tensor):
        super().__init__()
        self.conv = Conv(weight)

    def forward(self, z: torch.Tensor) -> torch.Tensor:
        return self.conv(F.interpolate(z, scale_factor=2, mode="bilinear", align_corners=False))


def split_level(level: nn.Module) -> tuple[nn.Module, Conv]:
    """A decoder level with a skip → (its ``W_u`` half on ``z``, its skip half with the bias)."""
    if isinstance(level, SubpixelLevel):
        return level.up, Conv(level.skip.weight, level.bias.view(-1))
    if isinstance(level, PlainLevel):
        w = level.conv.weight
        feats = w.shape[1] - w.shape[0]  # a skip has cout channels
        return PlainUp(w[:, :feats]), Conv(w[:, feats:], level.conv.bias)
    raise TypeError(f"not a decoder level: {type(level).__name__}")


class Fork:
    """The current stream and one side stream, with events between them; on CPU every
    step is a no-op and everything runs on the one stream."""

    def __init__(self, side: torch.cuda.Stream | None):
        self.side = side
        if side is not None:
            side.wait_stream(torch.cuda.current_stream())  # the inputs are written there

    def on_side(self):
        return torch.cuda.stream(self.side) if self.side else contextlib.nullcontext()

    def mark(self) -> torch.cuda.Event | None:
        """An event after the current stream's work so far (None on CPU)."""
        if self.side is None:
            return None
        event = torch.cuda.Event()
        event.record()
        return event

    @staticmethod
    def wait(event: torch.cuda.Event | None) -> None:
        if event is not None:
            torch.cuda.current_stream().wait_event(event)

    def join(self) -> None:
        if self.side is not None:
            torch.cuda.current_stream().wait_stream(self.side)


class StreamedRenderer(nn.Module):
    """A :class:`SubpixelRenderer` (of a network with skips) cut into the segments the
    module docstring says; same inputs and outputs. Each decoder level keeps the form it has
    there (sub-pixel or plain); only its skip half moves to the side stream."""

    def __init__(self, net: SubpixelRenderer):
        super().__init__()
        if not net.config.skips:
            raise ValueError("two streams need a network with skips (ModelConfig.skips)")
        self.config, self.in_channels = net.config, net.in_channels
        self.b, self.planes, self.colours = net.b, net.planes, net.colours
        self.encoder, self.light, self.fuse = net.encoder, net.light, net.fuse
        w = net.dec0.weight
        feats = w.shape[1] - w.shape[0]
        self.bottom = Conv(w[:, :feats])
        skips = [Conv(w[:, feats:], net.dec0.bias)]
        *decoder, self.out = net.levels
        halves = [split_level(level) for level in decoder]
        self.ups = nn.ModuleList(up for up, _ in halves)
        self.skips = nn.ModuleList(skips + [skip for _, skip in halves])
        self.segments = self.segment_functions()
        self._side: dict[torch.device, torch.cuda.Stream] = {}

    def segment_functions(self, wrap=lambda f: f) -> dict:
        """The segments, each through ``wrap``; a list of one function per skip convolution
        and per decoder level, so that each compiles to its own graph."""
        return {
            "encode": wrap(self.encode),
            "plane": wrap(self.plane),
            "skip": [wrap(lambda e, i=i: self.skips[i](e)) for i in range(len(self.skips))],
            "bottleneck": wrap(self.bottleneck),
            "level": [
                wrap(lambda p, k, i=i: self.ups[i](F.relu(p + k))) for i in range(len(self.ups))
            ],
            "output": wrap(self.output),
        }

    def compile_segments(self, **options) -> StreamedRenderer:
        """Each segment through ``torch.compile(**options)``; returns self.

        Dynamo keeps at most ``recompile_limit`` graphs (8 by default) per code object, and
        the skip segments share one: a graph per skip convolution per instance (a batch size
        of ``trainer.rendering.infer.GraphedRenderer``). So this raises the process's limit to
        64."""
        torch._dynamo.config.recompile_limit = max(torch._dynamo.config.recompile_limit, 64)
        self.segments = self.segment_functions(lambda f: torch.compile(f, **options))
        return self

    def encode(self, maps: torch.Tensor) -> list[torch.Tensor]:
        x = maps
        if x.shape[1] < self.in_channels:
            x = F.pad(x, (0, 0, 0, 0, 0, self.in_channels - x.shape[1]))
        features = []
        for enc in self.encoder:
            x = enc.relu(x)
            features.append(x)
        return features

    def plane(self, light: torch.Tensor) -> torch.Tensor:
        return self.light(light).view(-1, 1, self.b, self.b)

    def bottleneck(self, deepest: torch.Tensor, plane: torch.Tensor) -> torch.Tensor:
        planes = plane.to(deepest.dtype).expand(-1, self.planes, -1, -1)
        return self.bottom(F.relu(self.fuse(torch.cat([deepest, planes], 1))))

    def output(self, p: torch.Tensor, k: torch.Tensor) -> torch.Tensor:
        return torch.sigmoid(self.out(F.relu(p + k)))[:, : self.colours]

    def side_stream(self, device: torch.device) -> torch.cuda.Stream | None:
        if device.type != "cuda":
            return None
        if device not in self._side:
            self._side[device] = torch.cuda.Stream(device)
        return self._side[device]

    def forward(self, maps: torch.Tensor, light: torch.Tensor) -> torch.Tensor:
        run, fork = self.segments, Fork(self.side_stream(maps.device))
        with fork.on_side():
            plane = run["plane"](light)
            plane_done = fork.mark()
        features = run["encode"](maps)
        encoded = fork.mark()
        ks = []
        with fork.on_side():
            fork.wait(encoded)
            for i, feature in enumerate(reversed(features)):
                ks.append((run["skip"][i](feature), fork.mark()))
        fork.wait(plane_done)
        p = run["bottleneck"](features[-1], plane)
        for i, (k, done) in enumerate(ks[:-1]):
            fork.wait(done)
            p = run["level"][i](p, k)
        k, done = ks[-1]
        fork.wait(done)
        image = run["output"](p, k)
        fork.join()  # before the tensors the side stream read or wrote are let go
        return image


def streamed_network(
    model, compile: bool = False, align: int = 8, subpixel: bool = False
) -> nn.Module:
    """The paper's network on two streams as a CUDA graph takes it: BatchNorm folded, every
    level in its plain form (``subpixel``: its sub-pixel form) with aligned channels, the skip
    halves and the light MLP on the side stream, bf16 channels_last, compiled segment by
    segment with ``compile``."""
    start = 0 if subpixel else model.config.resolution
    net = fast_layers(model, subpixel=True, subpixel_from=start, align=align)
    net = StreamedRenderer(net).to(torch.bfloat16, memory_format=torch.channels_last)
    if not compile:
        return net
    return net.compile_segments(mode="max-autotune-no-cudagraphs", dynamic=False)
