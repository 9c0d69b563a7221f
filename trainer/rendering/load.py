"""A trained renderer from a file: a checkpoint or run folder (torch), or an exported model
(ONNX Runtime)."""

from __future__ import annotations

from trainer import checkpoint
from trainer.rendering.base import MapsRenderer
from trainer.rendering.infer import Renderer
from trainer.rendering.onnx_renderer import OnnxRenderer


def load_renderer(
    path, device: str = "auto", weights: str = "auto", graph: bool = False
) -> MapsRenderer:
    """The renderer of ``path``: a checkpoint or a run folder (:class:`Renderer`, torch on
    ``device``, with the checkpoint's ``weights``: :func:`trainer.checkpoint.weights`; with
    ``graph``, single frames through its CUDA graph), or a model ``trainer export`` wrote
    (``.onnx``: :class:`trainer.rendering.onnx_renderer.OnnxRenderer`, ONNX Runtime on the CPU, with
    the weights it was exported with)."""
    if str(path).lower().endswith(".onnx"):
        if weights != "auto":
            raise checkpoint.CheckpointError(
                f"{path}: an exported model holds the one set of weights it was exported "
                "with (trainer export --weights chooses them)"
            )
        if graph:
            raise ValueError(f"{path}: a CUDA graph is captured from a torch checkpoint, not "
                             "from an exported model")  # fmt: skip
        return OnnxRenderer.load(path, device)
    return Renderer.from_checkpoint(path, device, weights, graph)
