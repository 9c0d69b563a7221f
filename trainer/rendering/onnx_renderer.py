"""A model ``trainer export`` wrote, as a renderer: ``trainer render`` and ``trainer viewer``
take a ``.onnx`` file where they take a checkpoint and run it in ONNX Runtime on CPU, so the
file a tool or an engine will run is seen as it renders, and on CPU at small sizes it is
the faster network (``docs/benchmarks.md``, "ONNX Runtime").

:class:`OnnxRenderer` has the surface of :class:`trainer.rendering.infer.Renderer` those commands
use: ``render_batch``, ``render``, ``tonemap``, ``config``, ``device``, ``runtime``, ``step``,
``catalog`` and ``screen_uv()``, so ``trainer eval`` scores it too. Everything it needs comes
from the file (its ``shaderball.*`` metadata: resolution, model configuration, tonemap,
checkpoint step, the run's catalog of stores and held-out materials) and from the screen UV layout
``trainer export`` writes beside it (``<name>.screen_uv.npz``), read when asked for.
"""

from __future__ import annotations

import json
import os
from pathlib import Path

import numpy as np
import torch

from render_jobs.screen_uv import ScreenUV
from storage.extras import require
from storage.schema import PACKED_CHANNELS
from trainer.checkpoint import CheckpointError
from trainer.model import ModelConfig, check_inputs
from trainer.rendering.base import MapsRenderer
from trainer.targets import TURBIDITY_SCALE, Tonemap

#: the metadata keys a model must carry to be rendered here
INPUTS = ("maps", "sun", "turbidity")

OUTPUT = "image"

REQUIRED = ("shaderball.model_config", "shaderball.tonemap")


class OnnxRenderer(MapsRenderer):
    """An exported model in an ONNX Runtime session on CPU."""

    runtime = "ONNX Runtime"

    def __init__(self, session, meta: dict[str, str], path: Path):
        self.session, self.path = session, path
        self.config = ModelConfig(**json.loads(meta["shaderball.model_config"]))
        self.tonemap = Tonemap.from_dict(json.loads(meta["shaderball.tonemap"]))
        step = meta.get("shaderball.checkpoint_step", "")
        self.step = int(step) if step.isdigit() else None
        self.weights = meta.get("shaderball.weights", "trained")
        catalog = meta.get("shaderball.catalog")
        self.catalog = json.loads(catalog) if catalog else None
        self.device = torch.device("cpu")

    @classmethod
    def load(cls, path: str | os.PathLike, device: str = "auto") -> OnnxRenderer:
        """The model at ``path``; a :class:`CheckpointError` in one line for a file that is
        missing, not ONNX, or not a model ``trainer export`` wrote, or a ``device`` other
        than the CPU; :class:`storage.extras.MissingExtra` without onnxruntime."""
        p = Path(path)
        if device not in ("auto", "cpu"):
            raise CheckpointError(f"{p}: an .onnx model runs on the CPU here, not {device}")
        if not p.is_file():
            raise CheckpointError(f"{p}: no such model")
        require("an .onnx model", "onnxruntime")
        import onnxruntime as ort

        try:
            options = ort.SessionOptions()
            # its threads sleep between runs: spinning, they took the cores from the torch
            # mapping of the next edit (a tiling edit's mapping 2x slower in the viewer)
            options.add_session_config_entry("session.intra_op.allow_spinning", "0")
            session = ort.InferenceSession(str(p), options, providers=["CPUExecutionProvider"])
        except Exception as exc:  # noqa: BLE001 - ONNX Runtime raises its own several types
            lines = [line for line in str(exc).splitlines() if line.strip()]
            why = lines[0] if lines else type(exc).__name__
            raise CheckpointError(f"{p}: not a model ONNX Runtime can load ({why})") from None
        meta = session.get_modelmeta().custom_metadata_map
        missing = [k for k in REQUIRED if k not in meta]
        names = tuple(i.name for i in session.get_inputs())
        if missing or names != INPUTS or [o.name for o in session.get_outputs()] != [OUTPUT]:
            raise CheckpointError(
                f"{p}: not a model trainer export wrote (it takes {', '.join(names)}; "
                f"a shaderball model takes {', '.join(INPUTS)} and carries {REQUIRED[0]})"
            )
        try:
            return cls(session, meta, p)
        except (ValueError, TypeError) as exc:  # bad JSON, fields ModelConfig does not take
            raise CheckpointError(f"{p}: its shaderball metadata is unreadable ({exc})") from None

    @property
    def no_layout(self) -> str:
        return f"no screen UV layout beside the model ({layout_path(self.path).name})"

    def screen_uv(self):
        """The :class:`render_jobs.screen_uv.ScreenUV` beside the model, or ``None``."""
        beside = layout_path(self.path)
        if not beside.is_file():
            return None

        return ScreenUV.from_bytes(beside.read_bytes(), str(beside))

    def render_batch(self, maps: torch.Tensor, light: torch.Tensor) -> torch.Tensor:
        """``maps (N, 11, H, W) uint8`` + ``light (N, 4)`` → ``(N, 3, H, W) float32`` in [0, 1]."""
        maps, light = maps.cpu(), light.cpu().float()
        if maps.dim() != 4 or maps.shape[1] != PACKED_CHANNELS or maps.dtype != torch.uint8:
            raise ValueError(
                f"maps are {maps.dtype} {tuple(maps.shape)}, expected stored maps: "
                f"(N, {PACKED_CHANNELS}, H, W) uint8"
            )
        n, _, h, w = maps.shape  # the network's input shape, checked without making it
        check_inputs(self.config, torch.empty(()).expand(n, self.config.in_channels, h, w), light)
        feed = {
            "maps": np.ascontiguousarray(maps.numpy()),
            "sun": np.ascontiguousarray(light[:, :3].numpy()),
            "turbidity": np.ascontiguousarray((light[:, 3] * TURBIDITY_SCALE).numpy()),
        }
        (image,) = self.session.run([OUTPUT], feed)
        return torch.from_numpy(image)


def layout_path(out: Path) -> Path:
    """Where the screen UV layout of the model at ``out`` goes."""
    return out.with_name(out.stem + ".screen_uv.npz")
