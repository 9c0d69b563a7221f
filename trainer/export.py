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
the images of the torch :class:`trainer.infer.Renderer` on CPU before it keeps it. The file's
metadata (``metadata_props``) carries ``shaderball.*`` keys: the resolution, tonemap, model
configuration and checkpoint step, and the inputs' meaning.

A new material's maps become ``maps`` through the checkpoint's screen UV layout
(``trainer.mapping.ScreenMapper``); :func:`export` writes that layout beside the model
(``<name>.screen_uv.npz``: ``uv``, ``hit`` and ``meta``, as
:meth:`render_jobs.screen_uv.ScreenUV.to_bytes` writes it) when the checkpoint carries one.
"""

from __future__ import annotations

import copy
import json
import logging
import os
import warnings
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
from torch import nn

from storage.backend import create_beside, write_atomic
from trainer.infer import Renderer
from trainer.model import NeuralRenderer, fold_batchnorm
from trainer.targets import TURBIDITY_SCALE, model_inputs

INPUTS = ("maps", "sun", "turbidity")
OUTPUT = "image"
#: the largest difference from the torch renderer an exported model may show (fp32 both; seen:
#: under 1e-6)
TOLERANCE = 1e-4
#: the ONNX opset written: torch's exporter's own (its conversion to older opsets fails on
#: this network's Resize and falls back to 18); ONNX Runtime 1.14 and later run it
OPSET = 18


class ExportError(RuntimeError):
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


def metadata(renderer: Renderer) -> dict[str, str]:
    """The ``shaderball.*`` metadata the model file carries."""
    state = getattr(renderer, "state", {})
    return {
        "shaderball.resolution": str(renderer.config.resolution),
        "shaderball.model_config": json.dumps(renderer.config.to_dict()),
        "shaderball.tonemap": json.dumps(renderer.tonemap.to_dict()),
        "shaderball.checkpoint_step": str(state.get("step", "")),
        "shaderball.inputs": (
            "maps (N, 11, R, R) uint8 stored maps: diffuse, specular (sRGB), roughness, "
            "normal ((n + 1) / 2), coverage (not read); sun (N, 3) float32 direction, z up; "
            "turbidity (N,) float32"
        ),
        "shaderball.output": "image (N, 3, R, R) float32 in [0, 1], display sRGB (tonemap)",
    }


def save_onnx(
    module: nn.Module,
    inputs: dict[str, torch.Tensor],
    output: str,
    path: str | os.PathLike,
    metadata: dict[str, str] | None = None,
) -> None:
    """``module`` traced on ``inputs`` (named, in its argument order; the first dimension of
    each left free) and written to ``path`` as an ONNX model of :data:`OPSET` with
    ``metadata`` in its ``metadata_props``, quietly."""
    import onnx

    batch = torch.export.Dim("batch", min=1)
    log = logging.getLogger("torch.onnx")
    level = log.level
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # the exporter's deprecation and naming chatter
        log.setLevel(logging.ERROR)  # "torchvision is not installed", per operator
        try:
            program = torch.onnx.export(
                module, tuple(inputs.values()), input_names=list(inputs),
                output_names=[output], opset_version=OPSET, dynamo=True, verbose=False,
                dynamic_shapes=tuple({0: batch} for _ in inputs),
            )  # fmt: skip
        finally:
            log.setLevel(level)
    proto = program.model_proto
    for key, value in (metadata or {}).items():
        entry = proto.metadata_props.add()
        entry.key, entry.value = key, value
    onnx.save_model(proto, str(path))


def _trace(renderer: Renderer, path: Path) -> None:
    """The ONNX file of :func:`graph_of` at ``path``, with a free batch size and metadata."""
    ex = example_inputs(renderer.config.resolution, 2)
    inputs = {k: torch.from_numpy(ex[k]) for k in INPUTS}
    save_onnx(graph_of(renderer), inputs, OUTPUT, path, metadata(renderer))


def difference(session, renderer: Renderer, inputs: dict[str, np.ndarray]) -> float:
    """The largest absolute difference between the ONNX Runtime ``session`` on ``inputs``
    and the torch renderer on the same."""
    (got,) = session.run([OUTPUT], inputs)
    want = renderer.render(inputs["maps"], inputs["sun"], inputs["turbidity"])
    return float(np.abs(got - want).max())


def export(renderer: Renderer, out: str | os.PathLike) -> Exported:
    """Write ``renderer``'s network to ``out`` as ONNX (and its screen UV layout beside it),
    after checking that ONNX Runtime renders it as torch does (:data:`TOLERANCE`, on random
    inputs at batch 1 and 3). Nothing is left at ``out`` unless the check passed; an old
    file there is replaced whole."""
    out = Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = create_beside(out, ".onnx")
    os.close(fd)
    try:
        try:
            _trace(renderer, tmp)
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
    return Exported(out, layout, out.stat().st_size, worst)


def layout_path(out: Path) -> Path:
    """Where the screen UV layout of the model at ``out`` goes."""
    return out.with_name(out.stem + ".screen_uv.npz")


def _write_layout(renderer: Renderer, out: Path) -> Path | None:
    layout = renderer.screen_uv()
    if layout is None:  # a layout left beside an older export would not fit this model
        layout_path(out).unlink(missing_ok=True)
        return None
    data = layout.to_bytes()
    write_atomic(layout_path(out), lambda f: f.write(data))
    return layout_path(out)
