"""A trained renderer as an ONNX model: the network outside Python and outside torch (ONNX
Runtime in a tool or a game engine, a DCC plugin, the browser).

The graph is the whole of inference from stored maps, so a caller needs no shaderball code
to run it:

- input ``maps``: ``(N, 11, R, R) uint8``, stored maps (``storage.schema``: diffuse and
  specular sRGB-encoded, roughness, normal encoded ``(n + 1) / 2``, coverage; the coverage
  channel is not read);
- input ``sun``: ``(N, 3) float32``, the sun direction, z up (normalised in the graph; it
  must not be zero);
- input ``turbidity``: ``(N,) float32``, the sky turbidity (1 to 10 in training);
- output ``image``: ``(N, 3, R, R) float32`` in [0, 1], display-ready sRGB (the checkpoint's
  tonemap, ``trainer.targets.Tonemap``).

``N`` is free; ``R`` is the checkpoint's resolution. The network is the checkpoint's in fp32
with BatchNorm folded, and :func:`export` checks in ONNX Runtime that the written model gives
the images of the torch :class:`trainer.rendering.infer.Renderer` on CPU before it keeps it. The
file's metadata (``metadata_props``) carries ``shaderball.*`` keys: the resolution, tonemap, model
configuration and checkpoint step, the run's catalog (its stores and held-out materials,
which ``trainer eval`` scores the file on), and the inputs' meaning.

The model is ONNX opset 18 by default, from torch's dynamo exporter; an older opset, down to
11, for importers that read no newer, comes from torch's TorchScript exporter. Both are
checked the same way.

A new material's maps become ``maps`` through the checkpoint's screen UV layout
(``trainer.rendering.mapping.ScreenMapper``); :func:`export` writes that layout beside the model
(``<name>.screen_uv.npz``: ``uv``, ``hit`` and ``meta``, as
:meth:`render_jobs.screen_uv.ScreenUV.to_bytes` writes it) when the checkpoint carries one.
"""

from __future__ import annotations

import copy
import io
import json
import logging
import os
import warnings
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
from torch import nn

from shaderball.errors import UserError
from storage.backend import create_beside, write_atomic
from trainer.model import NeuralRenderer, fold_batchnorm
from trainer.rendering.infer import Renderer
from trainer.rendering.onnx_renderer import INPUTS, OUTPUT, layout_path
from trainer.targets import TURBIDITY_SCALE, model_inputs

#: the largest difference from the torch renderer an exported model may show (fp32 both; seen:
#: under 1e-6)
TOLERANCE = 1e-4
#: the ONNX opset written by default: torch's dynamo exporter's own (ONNX Runtime 1.14 and
#: later run it)
OPSET = 18
#: the oldest opset offered (the network's ``Resize`` needs 11), for importers that stop short
#: of 18 (Unity Sentis 1.x reads 7 to 15). Opsets below :data:`OPSET` are written by
#: torch's TorchScript exporter: the dynamo exporter's conversion to them fails on ``Resize``.
MIN_OPSET = 11


class ExportError(UserError, RuntimeError):
    """The model could not be exported, or the export does not render as the checkpoint."""


class StoredMapsGraph(nn.Module):
    """``(maps uint8, sun, turbidity) → image``: :meth:`Renderer.render`'s preprocessing
    (:func:`trainer.targets.model_inputs`, :func:`trainer.targets.light_vector`) and the
    network as one module, for tracing."""

    def __init__(self, net: nn.Module, roughness_channels: int):
        super().__init__()
        self.net = net
        self.roughness_channels = roughness_channels

    def forward(self, maps: torch.Tensor, sun: torch.Tensor, turbidity: torch.Tensor):
        x = model_inputs(maps, self.roughness_channels)
        direction = sun / torch.linalg.vector_norm(sun, dim=1, keepdim=True)
        light = torch.cat([direction, (turbidity / TURBIDITY_SCALE)[:, None]], 1)
        return self.net(x, light)


def graph_of(renderer: Renderer) -> StoredMapsGraph:
    """The module that is exported: the checkpoint's network in fp32 on CPU, BatchNorm folded
    (the Zsolnai-Fehér baseline as it is)."""
    model = renderer.model
    net = fold_batchnorm(model) if isinstance(model, NeuralRenderer) else copy.deepcopy(model)
    return StoredMapsGraph(net.to("cpu").float(), renderer.config.roughness_channels).eval()


def example_inputs(resolution: int, n: int, seed: int = 0) -> dict[str, np.ndarray]:
    """``n`` random inputs of the exported graph: uniform random map bytes, suns on the upper
    hemisphere, turbidities in [1, 10]."""
    rng = np.random.default_rng(seed)
    sun = rng.normal(size=(n, 3))
    sun[:, 2] = np.abs(sun[:, 2]) + 0.1
    return {
        "maps": rng.integers(0, 256, (n, 11, resolution, resolution), dtype=np.uint8),
        "sun": sun.astype(np.float32),
        "turbidity": rng.uniform(1.0, 10.0, n).astype(np.float32),
    }


@dataclass(frozen=True)
class Exported:
    """What :func:`export` wrote and how close it renders to the torch renderer."""

    model: Path
    screen_uv: Path | None
    bytes: int
    max_difference: float
    opset: int


def metadata(renderer: Renderer, catalog: bool = True) -> dict[str, str]:
    """The ``shaderball.*`` metadata the model file carries (without the run's catalog of
    stores when not ``catalog``)."""
    meta = {
        "shaderball.resolution": str(renderer.config.resolution),
        "shaderball.model_config": json.dumps(renderer.config.to_dict()),
        "shaderball.tonemap": json.dumps(renderer.tonemap.to_dict()),
        "shaderball.checkpoint_step": "" if renderer.step is None else str(renderer.step),
        "shaderball.weights": renderer.weights,  # the run's average or its trained weights
        "shaderball.inputs": (
            "maps (N, 11, R, R) uint8 stored maps: diffuse, specular (sRGB), roughness, "
            "normal ((n + 1) / 2), coverage (not read); sun (N, 3) float32 direction, z up; "
            "turbidity (N,) float32"
        ),
        "shaderball.output": "image (N, 3, R, R) float32 in [0, 1], display sRGB (tonemap)",
    }
    if catalog and renderer.catalog is not None:
        # the run's stores and held-out materials: `trainer eval` scores the file on them
        meta["shaderball.catalog"] = json.dumps(renderer.catalog)
    return meta


def save_onnx(
    module: nn.Module,
    inputs: dict[str, torch.Tensor],
    output: str,
    path: str | os.PathLike,
    metadata: dict[str, str] | None = None,
    opset: int = OPSET,
) -> None:
    """``module`` traced on ``inputs`` (named, in its argument order; the first dimension of
    each, and of ``output``, left free) and written to ``path`` as an ONNX model of ``opset``
    (:data:`MIN_OPSET` to :data:`OPSET`) with ``metadata`` in its ``metadata_props``,
    quietly."""
    import onnx

    if not MIN_OPSET <= opset <= OPSET:
        raise ValueError(f"opset {opset} is not offered (only {MIN_OPSET} to {OPSET})")
    log = logging.getLogger("torch.onnx")
    level = log.level
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # deprecation, naming and tracer chatter
        log.setLevel(logging.ERROR)  # "torchvision is not installed", per operator
        try:
            trace = _dynamo if opset == OPSET else _torchscript
            proto = trace(module, inputs, output, opset)
        finally:
            log.setLevel(level)
    for key, value in (metadata or {}).items():
        entry = proto.metadata_props.add()
        entry.key, entry.value = key, value
    onnx.save_model(proto, str(path))


def _dynamo(module: nn.Module, inputs: dict[str, torch.Tensor], output: str, opset: int):
    batch = torch.export.Dim("batch", min=1)
    program = torch.onnx.export(
        module, tuple(inputs.values()), input_names=list(inputs), output_names=[output],
        opset_version=opset, dynamo=True, verbose=False,
        dynamic_shapes=tuple({0: batch} for _ in inputs),
    )  # fmt: skip
    return program.model_proto


def _torchscript(module: nn.Module, inputs: dict[str, torch.Tensor], output: str, opset: int):
    import onnx

    buffer = io.BytesIO()
    torch.onnx.export(
        module, tuple(inputs.values()), buffer, input_names=list(inputs), output_names=[output],
        opset_version=opset, dynamo=False, verbose=False,
        dynamic_axes={name: {0: "batch"} for name in [*inputs, output]},
    )  # fmt: skip
    proto = onnx.load_model_from_string(buffer.getvalue())
    _restore_unused_inputs(proto, inputs)
    return proto


def _restore_unused_inputs(proto, inputs: dict[str, torch.Tensor]) -> None:
    """Put back, in ``inputs``' order, the inputs the TorchScript exporter drops when the
    graph does not read them (the Zsolnai-Fehér baseline's sun and turbidity), so that
    every exported model takes the same inputs."""
    from onnx import helper
    from onnx.helper import np_dtype_to_tensor_dtype

    kept = {i.name: i for i in proto.graph.input}
    declared = []
    for name, tensor in inputs.items():
        if name not in kept:
            dtype = np_dtype_to_tensor_dtype(tensor.numpy().dtype)
            shape = ["batch", *tensor.shape[1:]]
            kept[name] = helper.make_tensor_value_info(name, dtype, shape)
        declared.append(kept[name])
    del proto.graph.input[:]
    proto.graph.input.extend(declared)


def _trace(renderer: Renderer, path: Path, opset: int, catalog: bool) -> None:
    """The ONNX file of :func:`graph_of` at ``path``, with a free batch size and metadata."""
    ex = example_inputs(renderer.config.resolution, 2)
    inputs = {k: torch.from_numpy(ex[k]) for k in INPUTS}
    save_onnx(graph_of(renderer), inputs, OUTPUT, path, metadata(renderer, catalog), opset)


def difference(session, renderer: Renderer, inputs: dict[str, np.ndarray]) -> float:
    """The largest absolute difference between the ONNX Runtime ``session`` on ``inputs``
    and the torch renderer on the same."""
    (got,) = session.run([OUTPUT], inputs)
    want = renderer.render(inputs["maps"], inputs["sun"], inputs["turbidity"])
    return float(np.abs(got - want).max())


def export(
    renderer: Renderer, out: str | os.PathLike, opset: int = OPSET, catalog: bool = True
) -> Exported:
    """Write ``renderer``'s network to ``out`` as ONNX of ``opset`` (and its screen UV layout
    beside it), after checking that ONNX Runtime renders it as torch does (:data:`TOLERANCE`,
    on random inputs at batch 1 and 3); with the run's catalog of stores in its metadata
    unless not ``catalog``. Nothing is left at ``out`` unless the check passed; an old file
    there is replaced whole."""
    out = Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = create_beside(out, ".onnx")
    os.close(fd)
    try:
        try:
            _trace(renderer, tmp, opset, catalog)
        except Exception as exc:  # noqa: BLE001 - the exporter raises many types
            lines = str(exc).strip().splitlines()
            raise ExportError(
                f"the network could not be exported: {lines[0] if lines else type(exc).__name__}"
            ) from None
        import onnxruntime as ort

        reference = renderer
        if renderer.device.type != "cpu":  # fp32 proper: no TF32 convolutions
            model = copy.deepcopy(renderer.model)
            reference = Renderer(model, renderer.tonemap, torch.device("cpu"))
        session = ort.InferenceSession(str(tmp), providers=["CPUExecutionProvider"])
        worst = max(
            difference(session, reference, example_inputs(renderer.config.resolution, n, seed=n))
            for n in (1, 3)
        )
        del session  # the file is renamed or removed below
        if not worst <= TOLERANCE:
            raise ExportError(
                f"the exported model renders up to {worst:.2e} away from the checkpoint "
                f"(allowed {TOLERANCE:.0e}); nothing written"
            )
        with open(tmp, "rb+") as f:  # durable before it takes the name
            os.fsync(f.fileno())
        layout = _write_layout(renderer, out)
        os.replace(tmp, out)
    finally:
        tmp.unlink(missing_ok=True)
    return Exported(out, layout, out.stat().st_size, worst, opset)


def _write_layout(renderer: Renderer, out: Path) -> Path | None:
    layout = renderer.screen_uv()
    if layout is None:  # a layout left beside an older export would not fit this model
        layout_path(out).unlink(missing_ok=True)
        return None
    data = layout.to_bytes()
    write_atomic(layout_path(out), lambda f: f.write(data))
    return layout_path(out)
