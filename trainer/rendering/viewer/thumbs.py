"""Gallery pictures of file materials, without reading the whole material.

A gallery of 4K library materials would otherwise decode and convert every map of every
material (seconds each) to show 96-pixel pictures. The picture of a file material is its
colour map alone, decoded by Pillow and shrunk: the diffuse panel of a 5-panel PNG, the
diffuse map of a spec-gloss folder, the base colour of a metal-rough one (so a metal shows
its tint, where its diffuse map is black). Files Pillow cannot show as 8-bit colour (EXR,
16-bit grey) give ``None``, and the caller falls back to the material's maps.
"""

from __future__ import annotations

from pathlib import Path

from PIL import Image

from render_jobs.errors import MaterialError
from render_jobs.materials.files import PANELS
from render_jobs.materials.library import plan_folder

#: Pillow modes whose conversion to RGB keeps the picture (8-bit colour or grey)
_SHOWN = ("RGB", "RGBA", "L", "LA", "P")


def colour_preview(path: Path, size: int) -> Image.Image | None:
    """The colour map of the material at ``path`` (a 5-panel file or a per-map folder),
    RGB, at most ``size`` pixels a side; ``None`` when it cannot be shown this way."""
    try:
        if path.is_dir():
            files = plan_folder(path).files
            source, panel = files.get("diffuse") or files["basecolor"], None
        else:
            source, panel = path, PANELS.index("diffuse")
        with Image.open(source) as img:
            if img.mode not in _SHOWN:
                return None
            img.draft("RGB", (size * (5 if panel is not None else 1), size))  # JPEG: scaled
            if panel is not None:
                w, h = img.size
                if w != 5 * h:
                    return None
                img = img.crop((panel * h, 0, (panel + 1) * h, h))
            pic = img.convert("RGB")
    except (OSError, KeyError, ValueError, MaterialError, Image.DecompressionBombError):
        return None
    pic.thumbnail((size, size))
    return pic
