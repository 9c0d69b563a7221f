"""OpenEXR reading and writing (the ``OpenEXR`` package; no ``bpy``).

Arrays are ``(C, H, W) float32`` with row 0 at the top of the image.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import OpenEXR

_ORDER = "RGBAXYZV"


def read_layers(path: str | Path) -> dict[str, np.ndarray]:
    """A (multilayer) EXR as ``{layer: (C, H, W) float32}``.

    Blender names channels ``ViewLayer.<pass>.<R|G|B|A|X>``; the view-layer prefix is dropped
    and channels are ordered R, G, B, A (value passes have one channel, X).
    """
    with OpenEXR.File(str(path), separate_channels=True) as f:
        channels = {name: ch.pixels for name, ch in f.channels().items()}
    grouped: dict[str, dict[str, np.ndarray]] = {}
    for name, pixels in channels.items():
        parts = name.split(".")
        layer = parts[-2] if len(parts) >= 2 else ""
        grouped.setdefault(layer, {})[parts[-1]] = pixels
    out = {}
    for layer, chans in grouped.items():
        keys = sorted(chans, key=lambda c: (_ORDER.find(c) if c in _ORDER else 99, c))
        out[layer] = np.stack([np.asarray(chans[k], dtype=np.float32) for k in keys])
    return out


def write_exr(path: str | Path, channels: dict[str, np.ndarray]) -> None:
    """Write ``{name: (H, W) float32}`` channels to a ZIP-compressed scanline EXR."""
    header = {"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage}
    data = {k: np.ascontiguousarray(v, dtype=np.float32) for k, v in channels.items()}
    OpenEXR.File(header, data).write(str(path))


def write_image_exr(path: str | Path, image: np.ndarray) -> None:
    """Write a ``(C, H, W)`` array (C = 1 → Y, C = 3 → R, G, B) as an EXR."""
    names = {1: "Y", 3: "RGB", 4: "RGBA"}.get(image.shape[0])
    if names is None:
        raise ValueError(f"cannot write {image.shape[0]} channels as an image")
    write_exr(path, {c: image[i] for i, c in enumerate(names)})
