"""The viewer's frames: a material (with edits) under a light, through the trained network,
timed in three parts. Plain code: no web server in it (``benchmarks/viewer.py`` times it).

- **mapping**: the material's texture maps UV-mapped to the network's input, with its edits
  (:class:`trainer.rendering.mapping.ScreenMapper`). Four caches: the prepared textures per material
  (the one copy of its textures that the viewer keeps: the library hands them over), the
  looked-up sub-samples per (material, tiling), so that an edit of values (tints,
  scales, normal strength) costs only the mapper's ``finish``, the last result per
  (material, tiling), so that an edit of one map's values (a slider moving) maps only that
  map's channels again (``finish_channels``: the same bytes), and the result per
  (material, edits), so that moving the sun costs no mapping;
- **network**: the trained network (:class:`trainer.rendering.infer.Renderer`, its fp32 inference
  path) on the mapped maps and the light;
- **encoding**: the image's bytes (JPEG while the page follows the sun; PNG, with the
  material and light in its metadata, when saved).
"""

from __future__ import annotations

import io
import json
import time
from dataclasses import dataclass
from functools import partial

import numpy as np
import torch
from PIL import Image
from PIL.PngImagePlugin import PngInfo

from render_jobs.errors import MaterialError
from render_jobs.specs import Sun
from render_jobs.tonemap import to_uint8
from trainer.rendering.infer import Renderer
from trainer.rendering.mapping import CHANNEL_GROUPS
from trainer.rendering.viewer.materials import Edits, Library, direction
from trainer.rendering.viewer.recent import Recent
from trainer.scoring import psnr
from trainer.targets import light_vector

JPEG_QUALITY = 92
FORMATS = ("jpeg", "png")
#: the most bytes of prepared textures kept (8-bit: 10.5 MB a 1K material, 168 MB a 4K one,
#: so the count bounds 4K ones: 8, 1.3 GB)
PREPARED_BYTES = 2 << 30


@dataclass(frozen=True)
class Light:
    """The sun as the page gives it: azimuth (degrees from +X towards +Y), elevation above
    the horizon (degrees), sky turbidity."""

    azimuth: float = 240.0
    elevation: float = 40.0
    turbidity: float = 3.0

    def __post_init__(self) -> None:
        Sun(direction(self.azimuth, self.elevation), self.turbidity)  # raises ValueError

    @classmethod
    def from_query(cls, query) -> Light:
        values = {}
        for key, name in (("az", "azimuth"), ("el", "elevation"), ("t", "turbidity")):
            if key in query:
                try:
                    values[name] = float(query[key])
                except ValueError:
                    raise ValueError(f"{key}={query[key]!r} is not a number") from None
        if not 0.5 <= values.get("elevation", 40.0) <= 90.0:
            raise ValueError(f"el={values['elevation']:g}: the sun must be 0.5 to 90° up")
        return cls(**values)

    @property
    def vector(self) -> np.ndarray:
        return light_vector(direction(self.azimuth, self.elevation), self.turbidity)


@dataclass
class Frame:
    """An encoded image and what it took, in milliseconds (``mapping`` is 0 when cached)."""

    body: bytes
    content_type: str
    image: np.ndarray  # (H, W, 3) uint8
    mapping_ms: float
    network_ms: float
    encoding_ms: float
    cached: bool

    def server_timing(self) -> str:
        """The ``Server-Timing`` header the page reads."""
        return (
            f'map;dur={self.mapping_ms:.2f};desc="{"cached" if self.cached else "mapping"}", '
            f"net;dur={self.network_ms:.2f}, enc;dur={self.encoding_ms:.2f}"
        )


class Engine:
    """Frames of one checkpoint. ``mapper`` is ``None`` when no screen UV layout came with
    the checkpoint or a store: then only stored materials (their stored maps) render."""

    def __init__(self, renderer: Renderer, mapper, library: Library, checkpoint: str):
        self.renderer, self.mapper, self.library = renderer, mapper, library
        self.checkpoint = checkpoint
        self._maps = Recent(32)  # (material, edits) → mapped maps
        self._looked = Recent(2)  # (material, tiling) → looked-up sub-samples (16 MB at 400²)
        self._last = Recent(2)  # (material, tiling) → (edits, mapped maps): the last mapped
        self._prepared = Recent(8, PREPARED_BYTES)  # material → prepared textures

    def _sync(self) -> None:
        if self.renderer.device.type == "cuda":
            torch.cuda.synchronize()

    def maps(self, material_id: str, edits: Edits) -> tuple[torch.Tensor, float, bool]:
        """The network's input ``(1, 11, R, R) uint8`` on the device, the seconds mapping
        took, and whether it came from the cache."""
        key = (material_id, edits)
        hit = self._maps.get(key)
        if hit is not None:
            return hit, 0.0, True
        t0 = time.perf_counter()
        looked = self._looked.get((material_id, edits.tiling))
        if looked is None:
            prepared = self._prepared.get(material_id)
            if prepared is None:
                prepared = self._prepare(material_id, edits)
            if prepared is not None:
                looked = self.mapper.lookup(prepared, edits.tiling)
                self._looked.put((material_id, edits.tiling), looked)
        if looked is None:  # a stored material whose source files are not here
            packed = torch.from_numpy(np.array(self.library.stored_maps(material_id)))[None]
            packed = packed.to(self.renderer.device)
        else:
            packed = self._finish(material_id, looked, edits)
        self._sync()
        seconds = time.perf_counter() - t0
        self._maps.put(key, packed)
        return packed, seconds, False

    def _finish(self, material_id: str, looked: torch.Tensor, edits: Edits) -> torch.Tensor:
        """The maps of ``looked`` with ``edits``: from the last maps of this material and
        tiling, with the one map whose values changed mapped again, when only one did; else
        all of them (one filter over all channels is the cheaper then)."""
        key = (material_id, edits.tiling)
        last = self._last.get(key)
        changed = None if last is None else edits.groups_changed_from(last[0])
        if changed is not None and len(changed) <= 1:
            packed = last[1].clone()
            edited = edits.groups_changed_from(Edits())
            for group in changed:
                edit = partial(edits.edited, group) if group in edited else None
                channels = CHANNEL_GROUPS[group]
                packed[:, channels] = self.mapper.finish_channels(looked, channels, edit)
        else:
            packed = self.mapper.finish(looked, edits.adjust if edits.changes_values else None)
        self._last.put(key, (edits, packed))
        return packed

    def _prepare(self, material_id: str, edits: Edits) -> torch.Tensor | None:
        """The material's textures, prepared for the mapper and kept for the next edits;
        ``None`` (stored maps stand in) for a stored material whose files are not here."""
        tex = self.library.textures(material_id, keep=False)  # held once: prepared, below
        if tex is None:
            if not edits.identity:
                raise MaterialError(
                    f"{material_id}: its source maps cannot be read here, so it cannot be edited"
                )
            return None
        if self.mapper is None:
            raise MaterialError(
                "no screen UV layout came with the checkpoint or --store: only stored "
                "materials can be shown (farm screen-uv STORE adds one to a store)"
            )
        prepared = self.mapper.prepare(tex)
        self._prepared.put(material_id, prepared)
        return prepared

    def network(self, packed: torch.Tensor, light: np.ndarray) -> np.ndarray:
        """``(3, R, R) float32`` display image in [0, 1] of ``packed`` under ``light (4,)``."""
        return self._rendered(packed, light).cpu().numpy()

    def picture(self, packed: torch.Tensor, light: np.ndarray) -> np.ndarray:
        """``(R, R, 3) uint8``: :meth:`network`'s image as ``to_uint8`` makes it. On CUDA it
        is quantized on the device (:func:`to_uint8_tensor`): a quarter of the bytes come
        back, and the CPU is spared a float pass over the image. On the CPU numpy's pass
        stays: the tensor form gains nothing there (``benchmarks.viewer``)."""
        image = self._rendered(packed, light)
        if image.device.type == "cpu":
            return to_uint8(image.numpy())
        return to_uint8_tensor(image).cpu().numpy()

    def _rendered(self, packed: torch.Tensor, light: np.ndarray) -> torch.Tensor:
        return self.renderer.render_batch(packed, torch.from_numpy(light[None]))[0]

    def frame(self, material_id: str, edits: Edits, light: Light, fmt: str = "jpeg") -> Frame:
        if fmt not in FORMATS:
            raise ValueError(f"format {fmt!r} is not one of {FORMATS}")
        packed, map_s, cached = self.maps(material_id, edits)
        t0 = time.perf_counter()
        image = self.picture(packed, light.vector)
        t1 = time.perf_counter()
        buf = io.BytesIO()
        if fmt == "jpeg":
            Image.fromarray(image).save(buf, format="JPEG", quality=JPEG_QUALITY)
        else:
            meta = self.metadata(material_id, edits, light)
            Image.fromarray(image).save(buf, format="PNG", pnginfo=meta, compress_level=6)
        t2 = time.perf_counter()
        return Frame(
            buf.getvalue(), f"image/{fmt}", image, map_s * 1e3, (t1 - t0) * 1e3,
            (t2 - t1) * 1e3, cached,
        )  # fmt: skip

    def metadata(self, material_id: str, edits: Edits, light: Light) -> PngInfo:
        """PNG text chunks: the material (id, source, edits), the light and the checkpoint."""
        e = self.library.entry(material_id)
        info = PngInfo()
        material = {"id": e.id, "label": e.label, "kind": e.kind, "source": e.source,
                    "edits": edits.to_dict()}  # fmt: skip
        sun = {**light.__dict__, "direction": [round(c, 6) for c in light.vector[:3].tolist()]}
        info.add_text("shaderball:material", json.dumps(material))
        info.add_text("shaderball:light", json.dumps(sun))
        info.add_text("shaderball:checkpoint", self.checkpoint)
        info.add_text("Software", "shaderball trainer viewer")
        return info

    def truth(self, material_id: str, k: int) -> dict:
        """A stored material under its ``k``-th stored sun: the Cycles render, the network's
        image of the unedited material under exactly that sun, their |error| x 4 (PNG
        bytes) and the PSNR in the tonemapped display space ``trainer eval`` uses."""
        radiance, sun = self.library.truth(material_id, k)
        truth = self.renderer.tonemap(torch.from_numpy(radiance)[None])[0]
        e = self.library.entry(material_id)
        d, t = self.library.stores[e.store].light(sun["sample"])  # exact, not the page's angles
        packed, _, _ = self.maps(material_id, Edits())
        net = torch.from_numpy(self.network(packed, light_vector(d, t)))
        err = ((net - truth).abs().mean(0, keepdim=True) * 4.0).clamp(0, 1)
        return {
            "psnr": round(float(psnr(net[None], truth[None])[0]), 2),
            "truth": _png(to_uint8(truth.numpy())),
            "network": _png(to_uint8(net.numpy())),
            "error": _png(to_uint8(err.numpy())),
            "sun": sun,
        }


def to_uint8_tensor(image: torch.Tensor) -> torch.Tensor:
    """``render_jobs.tonemap.to_uint8`` for a ``(3, H, W)`` float32 tensor on its own device:
    ``(H, W, 3) uint8``, contiguous, the same bytes (the same float32 steps, each its own
    operation, as ``render_jobs.materials.maps.quantize_u8`` takes them)."""
    x = image.float().clamp(0.0, 1.0)
    x = x * 255.0
    x = x + 0.5
    return x.to(torch.uint8).permute(1, 2, 0).contiguous()


def _png(image: np.ndarray) -> bytes:
    buf = io.BytesIO()
    Image.fromarray(image).save(buf, format="PNG")
    return buf.getvalue()
