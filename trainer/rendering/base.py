"""What every renderer of a trained network offers (:class:`MapsRenderer`), and what runs on
any of them: mapping new materials onto the ball (:func:`material_mapper`) and rendering a
material under many suns (:func:`render_under`)."""

from __future__ import annotations

import numpy as np
import torch

from shaderball.errors import UserError
from storage.reader import Store
from trainer.model import ModelConfig
from trainer.rendering.mapping import ScreenMapper
from trainer.targets import Tonemap, light_vector


class MapsRenderer:
    """What ``trainer render``, ``trainer viewer`` and :func:`render_under` use of a renderer:
    :meth:`render_batch` (each kind's own), :meth:`render` over it, and ``config``
    (:class:`ModelConfig`), ``tonemap``, ``device``, ``runtime``, ``step`` (the
    checkpoint's, or ``None``), ``weights`` (``average`` or ``trained``: which of the run's,
    :func:`trainer.checkpoint.weights`), ``catalog`` (the run's stores and held-out split,
    :meth:`storage.catalog.Catalog.to_dict`, or ``None``) and ``screen_uv()``."""

    config: ModelConfig
    tonemap: Tonemap
    device: torch.device
    step: int | None
    catalog: dict | None
    weights: str = "trained"
    #: what runs the network, for people to read
    runtime = "torch"
    #: why ``screen_uv()`` gives ``None``
    no_layout = "the checkpoint carries no screen UV layout (its store had none)"

    def render_batch(self, maps: torch.Tensor, light: torch.Tensor) -> torch.Tensor:
        raise NotImplementedError

    def screen_uv(self):
        raise NotImplementedError

    def render(self, maps: np.ndarray, sun_direction, turbidity) -> np.ndarray:
        """Stored maps ``(11, H, W)`` or ``(N, 11, H, W) uint8`` under one sun (or ``N`` suns:
        ``sun_direction (N, 3)``, ``turbidity (N,)``) → ``(3, H, W)`` / ``(N, 3, H, W)``."""
        arr = np.asarray(maps)
        if arr.dtype != np.uint8:
            raise ValueError(f"maps must be stored uint8 maps, not {arr.dtype}")
        single = arr.ndim == 3
        batch = torch.from_numpy(np.array(arr[None] if single else arr))
        light = np.broadcast_to(light_vector(sun_direction, turbidity), (len(batch), 4))
        out = self.render_batch(batch, torch.from_numpy(np.array(light)))
        out = out.cpu().numpy()
        return out[0] if single else out


class NoScreenUV(UserError, ValueError):
    """A new material must be mapped, and no screen UV layout was given."""


def material_mapper(renderer: MapsRenderer, store: str | None = None):
    """A :class:`trainer.rendering.mapping.ScreenMapper` on the renderer's device, with the layout
    the
    renderer carries, else ``store``'s (which must fit the network's resolution)."""
    layout = renderer.screen_uv()
    if layout is None and store is not None:
        layout = Store(store).screen_uv()
    if layout is None:
        raise NoScreenUV(
            f"{renderer.no_layout}: pass --store with a store of the same resolution that "
            "has one (farm screen-uv STORE adds it)"
        )
    if layout.resolution != renderer.config.resolution:
        raise NoScreenUV(
            f"the screen UV layout is for {layout.resolution}², the network for "
            f"{renderer.config.resolution}²"
        )
    return ScreenMapper(layout, renderer.device)


#: frames a batch in :func:`render_under`
UNDER_BATCH = 8


def render_under(renderer: MapsRenderer, maps: np.ndarray, suns, batch: int = UNDER_BATCH):
    """One material's stored maps ``(11, H, W) uint8`` under each of ``suns``
    (:class:`render_jobs.specs.Sun`), ``batch`` at a time: an iterator of ``(3, H, W)``
    images in [0, 1], in the order of ``suns``."""
    suns = list(suns)
    for i in range(0, len(suns), batch):
        part = suns[i : i + batch]
        stack = np.ascontiguousarray(np.broadcast_to(maps, (len(part), *np.shape(maps))))
        directions = np.array([s.direction for s in part], np.float32)
        yield from renderer.render(stack, directions, np.array([s.turbidity for s in part]))
