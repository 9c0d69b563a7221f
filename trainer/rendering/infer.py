"""Inference: a trained neural renderer as a Python API over arrays and stored samples.

>>> r = Renderer.from_checkpoint("runs/demo")           # a run folder (latest) or a .pt file
>>> img = r.render(maps, sun_direction=(0, 0.5, 1), turbidity=3)   # (3, H, W) float32 in [0, 1]

``maps`` are stored maps, ``(11, H, W)`` or ``(N, 11, H, W) uint8`` (``storage.schema``); the
image is in the checkpoint's tonemapped display space (``trainer.targets.Tonemap``).
"""

from __future__ import annotations

import os

import torch

from render_jobs.screen_uv import ScreenUV
from trainer import checkpoint
from trainer.devices import pick_device
from trainer.model import ModelConfig, NeuralRenderer, fold_batchnorm
from trainer.networks import build_model
from trainer.rendering.base import MapsRenderer
from trainer.rendering.fastnet import SubpixelRenderer
from trainer.targets import Tonemap, model_inputs

#: the smallest resolution at which :class:`Renderer` runs the sub-pixel rewrite on CPU; below
#: it the folded original in channels_last is the faster (``benchmarks.infer`` on the CPU)
CPU_SUBPIXEL_FROM = 288


def inference_network(model: NeuralRenderer, device: torch.device) -> torch.nn.Module:
    """The fp32 network :class:`Renderer` runs on ``device``, BatchNorm folded. On CPU in
    channels_last: for the paper's network (``ModelConfig.plain``) from ``CPU_SUBPIXEL_FROM``
    up the exact sub-pixel rewrite of :mod:`trainer.rendering.fastnet`, else the original layout;
    elsewhere the original layout, where the uncompiled rewrite is the slower
    (``benchmarks.infer``)."""
    if not isinstance(model, NeuralRenderer):  # the baseline (trainer.zf) runs as it is
        return model.eval()
    folded = fold_batchnorm(model)
    if device.type != "cpu":
        return folded
    if model.config.plain and model.config.resolution >= CPU_SUBPIXEL_FROM:
        folded = SubpixelRenderer(folded)
    return folded.to(memory_format=torch.channels_last)


class Renderer(MapsRenderer):
    """A trained model in eval mode, with the tonemap it was trained against.

    It renders in fp32 through :func:`inference_network`: the same images as ``model`` to
    about 1e-7. With ``graph`` (CUDA, the paper's network), a single frame renders through
    :meth:`GraphedRenderer.fastest` instead: bf16, within the bound the tests hold the fast
    forms to, after a compile at start; batches still run in fp32. That is the viewer's
    choice (``trainer viewer --cuda-graph``), where one frame follows another; eval
    and render keep fp32."""

    def __init__(
        self, model: NeuralRenderer, tonemap: Tonemap, device: torch.device, graph: bool = False
    ):
        self.model = model.to(device).eval()
        self.net = inference_network(self.model, device)
        self.fmt = torch.channels_last if device.type == "cpu" else torch.contiguous_format
        self.tonemap = tonemap
        self.device = device
        self.graphed = None
        if graph:
            check_graphable(self.model, device)
            self.graphed = GraphedRenderer.fastest(self.model, 1)
            self.runtime = "torch, CUDA graph (bf16)"

    @classmethod
    def from_checkpoint(
        cls, path, device: str = "auto", weights: str = "auto", graph: bool = False
    ) -> Renderer:
        """The checkpoint (or run folder's latest) at ``path`` with its ``weights``
        (:func:`trainer.checkpoint.weights`: by default the run's average when it kept one);
        ``graph``: see the class."""
        state = checkpoint.load(path)
        model = build_model(ModelConfig(**state["model_config"]))
        try:
            which = checkpoint.chosen(state, weights)
        except checkpoint.CheckpointError as exc:
            raise checkpoint.CheckpointError(f"{path}: {exc}") from None
        model.load_state_dict(checkpoint.weights(state, which))
        r = cls(model, Tonemap.from_dict(state["tonemap"]), pick_device(device), graph)
        r.state, r.weights = state, which
        return r

    @property
    def step(self) -> int | None:
        """The training step of the checkpoint it was loaded from."""
        step = getattr(self, "state", {}).get("step")
        return None if step is None else int(step)

    @property
    def catalog(self) -> dict | None:
        """The run's stores and held-out split, as the checkpoint keeps them."""
        return getattr(self, "state", {}).get("catalog")

    @property
    def config(self) -> ModelConfig:
        return self.model.config

    def screen_uv(self):
        """The :class:`render_jobs.screen_uv.ScreenUV` the checkpoint carries, or ``None``."""
        raw = getattr(self, "state", {}).get("screen_uv")
        if raw is None:
            return None

        return ScreenUV.from_bytes(raw, "the checkpoint's screen UV layout")

    @torch.inference_mode()
    def render_batch(self, maps: torch.Tensor, light: torch.Tensor) -> torch.Tensor:
        """``maps (N, 11, H, W) uint8`` + ``light (N, 4)`` → ``(N, 3, H, W) float32`` in [0, 1]."""
        x = model_inputs(maps.to(self.device), self.config.roughness_channels)
        light = light.to(self.device, torch.float32)
        self.model.check_inputs(x, light)
        if self.graphed is not None and len(x) == 1:
            return self.graphed(x, light).float()  # a copy: the graph's output is overwritten
        return self.net(x.contiguous(memory_format=self.fmt), light).float()


def check_graphable(model: torch.nn.Module, device: torch.device) -> None:
    """Raise ``ValueError`` unless :class:`GraphedRenderer` can capture ``model`` on
    ``device``: the paper's network (:class:`NeuralRenderer`) on a CUDA device."""
    if device.type != "cuda":
        raise ValueError(f"a CUDA graph needs a CUDA device, not {device.type} (--device cuda)")
    if not isinstance(model, NeuralRenderer):
        raise ValueError(f"a CUDA graph is captured from the paper's network, not from "
                         f"{type(model).__name__}")  # fmt: skip


def fast_layers(
    model: NeuralRenderer,
    subpixel: bool = False,
    align: int = 8,
    edge_ring: bool = False,
    conv_relu: bool = False,
    light_sums: bool = False,
    fold_ring: bool = False,
) -> torch.nn.Module:
    """The fp32 layers of :func:`fast_network` (BatchNorm folded, and the sub-pixel rewrite
    when asked), before the cast and the compile; its keywords are :func:`fast_network`'s."""
    for name, asked in (("conv_relu", conv_relu), ("light_sums", light_sums),
                        ("edge_ring", edge_ring)):  # fmt: skip
        if asked and not subpixel:
            raise ValueError(f"{name} is a form of the subpixel network")
    if fold_ring and not edge_ring:
        raise ValueError("fold_ring is a form of the edge ring")
    if subpixel and not model.config.plain:
        raise ValueError("the sub-pixel rewrite is of the paper's network (no scene cues, "
                         "BatchNorm, no head)")  # fmt: skip
    net = fold_batchnorm(model)
    if subpixel:
        net = SubpixelRenderer(net, align).rings(edge=edge_ring, fold=fold_ring)
        net.fuse_relus(conv_relu)
        net.light_sums(light_sums)
    return net


def fast_network(model: NeuralRenderer, compile: bool = False, **layers) -> torch.nn.Module:
    """The network as the fast path runs it: BatchNorm folded, weights cast to bf16 once,
    channels_last (the scene cues stay fp32). ``subpixel``: the exact rewrite of
    :mod:`trainer.rendering.fastnet` (no upsampled or concatenated tensors; its channel
    counts, ``in_channels`` included, are padded to multiples of ``align`` with zero-weight
    channels, the shapes tensor cores take). With ``subpixel``: ``edge_ring``, its phases on
    zero-padded inputs and the rings as corrections two deep, and ``fold_ring`` each such
    correction as one batched product
    (:meth:`trainer.rendering.fastnet.SubpixelRenderer.rings`); ``conv_relu``, the encoder's
    convolutions and the bottleneck's last with their ReLU in one operator, on CUDA one cuDNN
    call (:meth:`trainer.rendering.fastnet.SubpixelRenderer.fuse_relus`); ``light_sums``, the
    light encoder's layers as sums that Inductor compiles into one kernel each
    (:class:`trainer.rendering.fastnet.SummedMLP`). ``compile``: compiled by Inductor
    (``max-autotune-no-cudagraphs``: pointwise work fused around tuned convolutions; minutes
    of autotuning at first use; :func:`compile_options`). Feed it bf16 channels_last
    inputs."""
    net = fast_layers(model, **layers)
    net = net.to(torch.bfloat16, memory_format=torch.channels_last)
    if not compile:
        return net
    return torch.compile(net, dynamic=False, options=compile_options())


#: what Inductor's autotuning weighs for the fast path: cuDNN's convolutions and cuBLAS's
#: GEMMs alone (``benchmarks/gpu.sh``'s default too). With Triton's templates as well
#: (Inductor's own default) a first compile takes many minutes
TUNED_BACKENDS = {"max_autotune_conv_backends": "ATEN", "max_autotune_gemm_backends": "ATEN"}


def compile_options(environ=os.environ) -> dict:
    """The Inductor options :func:`fast_network` compiles with: ``max-autotune-no-cudagraphs``,
    and :data:`TUNED_BACKENDS` but where ``TORCHINDUCTOR_MAX_AUTOTUNE_CONV_BACKENDS`` or
    ``_GEMM_`` is set in ``environ`` (then Inductor reads that)."""
    from torch._inductor import list_mode_options

    options = list_mode_options("max-autotune-no-cudagraphs")
    for key, value in TUNED_BACKENDS.items():
        if f"TORCHINDUCTOR_{key.upper()}" not in environ:
            options[key] = value
    return options


#: the keywords of :func:`fast_network` for the sub-pixel rewrite compiled, its rings as
#: edge corrections on zero-padded phases, the encoder's convolutions with their ReLU in one
#: cuDNN call
EDGE_RELU = {"compile": True, "subpixel": True, "edge_ring": True, "conv_relu": True}
#: the fastest form of the paper's network, batched and at batch 1: :data:`EDGE_RELU` with the
#: light encoder as sums and each ring one product (``benchmarks.infer``'s rows compare them)
FASTEST = EDGE_RELU | {"light_sums": True, "fold_ring": True}
#: the fast form of a network other than the paper's: BatchNorm folded where there is one,
#: bf16 (the scene cues stay fp32: ``trainer.scene.SceneInputs``), channels_last, compiled
COMPILED = {"compile": True}


class GraphedRenderer:
    """A CUDA-graph replay of the network at one batch size: the fast path for interactive use.

    The :func:`fast_network` (compiled with ``compile=True``) is captured, so no autocast
    casts run per call. ``__call__(x (N, C, H, W) float, light (N, 4))`` copies into static
    inputs, replays, and returns the static ``(N, 3, H, W) bfloat16`` output (overwritten by
    the next call); :meth:`replay` renders what the static inputs hold. CUDA only:
    ``benchmarks.infer`` runs it on a GPU; the CPU test suite checks the forms it captures.

    ``fast`` are :func:`fast_network`'s keywords, or ``net`` a network made otherwise (fed
    bf16 channels_last inputs); :meth:`fastest` captures the fastest form (:data:`FASTEST`)."""

    @classmethod
    def fastest(cls, model: NeuralRenderer, batch: int) -> GraphedRenderer:
        """The network in its fastest form, captured at ``batch``: the paper's network as
        :data:`FASTEST`, any other (scene cues, GroupNorm, a head) compiled as it is
        (:data:`COMPILED`): the sub-pixel rewrites know the paper's layers only."""
        return cls(model, batch, **(FASTEST if model.config.plain else COMPILED))

    def __init__(self, model: NeuralRenderer, batch: int, warmup: int = 3, net=None, **fast):
        if not torch.cuda.is_available() or next(model.parameters()).device.type != "cuda":
            raise RuntimeError("CUDA graphs need the model on a CUDA device")
        cfg = model.config
        dev = next(model.parameters()).device
        torch.backends.cudnn.benchmark = True
        fmt, bf16 = torch.channels_last, torch.bfloat16
        self.model = net = net if net is not None else fast_network(model, **fast)
        self.channels = cfg.in_channels  # the static input may have more, left zero
        width = getattr(net, "in_channels", cfg.in_channels)
        shape = (batch, width, cfg.resolution, cfg.resolution)
        self.x = torch.zeros(shape, device=dev, dtype=bf16).contiguous(memory_format=fmt)
        self.light = torch.zeros(batch, 4, device=dev, dtype=bf16)
        stream = torch.cuda.Stream()
        stream.wait_stream(torch.cuda.current_stream())
        with torch.cuda.stream(stream), torch.inference_mode():
            for _ in range(warmup):
                net(self.x, self.light)
        torch.cuda.current_stream().wait_stream(stream)
        self.graph = torch.cuda.CUDAGraph()
        with torch.cuda.graph(self.graph), torch.inference_mode():
            self.out = net(self.x, self.light)

    def __call__(self, x: torch.Tensor, light: torch.Tensor) -> torch.Tensor:
        self.x[:, : self.channels].copy_(x)
        self.light.copy_(light)
        return self.replay()

    def replay(self) -> torch.Tensor:
        """Render what the static inputs hold now: for a producer that writes its frames into
        ``x[:, :channels]`` (channels_last bfloat16) and ``light`` itself, with no copy in."""
        self.graph.replay()
        return self.out
