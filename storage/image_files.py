"""Image files the command lines write (``shards show``, ``trainer render``, ``trainer eval
--grid``).

The format comes from the file name and is checked before any work (:func:`image_format`),
so a misspelt name fails at once in one line rather than after a render or an evaluation.
Files are written whole (:func:`storage.backend.write_atomic`): a killed command leaves the
old file or none, never part of a picture.
"""

from __future__ import annotations

import os
from pathlib import Path

import click
from PIL import Image
from PIL.PngImagePlugin import PngInfo

from storage.backend import write_atomic

#: still pictures, by suffix
STILL = {".png": "PNG", ".jpg": "JPEG", ".jpeg": "JPEG", ".webp": "WEBP"}
#: animations, by suffix: animated PNG, GIF (256 colours a frame) and animated WebP
ANIMATED = {".png": "PNG", ".gif": "GIF", ".webp": "WEBP"}
#: the quality of lossy formats (JPEG, WebP)
QUALITY = 92


def image_format(path: str | os.PathLike, animated: bool = False) -> str:
    """PIL's format name for ``path``'s suffix; a ``ValueError`` naming the file and the
    suffixes allowed when it has none of them."""
    table = ANIMATED if animated else STILL
    fmt = table.get(Path(path).suffix.lower())
    if fmt is None:
        kind = "an animation" if animated else "a picture"
        *first, last = table
        raise ValueError(
            f"{str(path)!r} does not name {kind}: its name must end in {', '.join(first)} or {last}"
        )
    return fmt


def save_image(image: Image.Image, path: str | os.PathLike, text: dict[str, str] | None = None):
    """Write ``image`` to ``path`` whole, in the format its name says, with ``text`` as PNG
    text chunks (other formats carry none)."""
    fmt = image_format(path)
    write_atomic(path, lambda f: image.save(f, format=fmt, **_options(fmt, text)))


def save_animation(
    frames: list[Image.Image],
    path: str | os.PathLike,
    fps: float,
    text: dict[str, str] | None = None,
):
    """Write ``frames`` to ``path`` whole as an endless animation at ``fps``, in the format its
    name says, with ``text`` as PNG text chunks (other formats carry none)."""
    fmt = image_format(path, animated=True)
    if not frames:
        raise ValueError("an animation needs at least one frame")
    params = dict(save_all=True, append_images=frames[1:], duration=round(1000 / fps), loop=0)
    write_atomic(path, lambda f: frames[0].save(f, format=fmt, **params, **_options(fmt, text)))


def _options(fmt: str, text: dict[str, str] | None) -> dict:
    if fmt == "PNG":
        info = PngInfo()
        for key, value in (text or {}).items():
            info.add_text(key, value)
        return {"pnginfo": info}
    if fmt in ("JPEG", "WEBP"):
        return {"quality": QUALITY}
    return {}


def check_picture_name(path, option: str, animated: bool = False) -> None:
    """A usage error naming ``option``, before any work, when ``path`` (``None``: none given)
    names no picture format the CLIs write (:func:`image_format`), or lies in a folder that
    does not exist (a typo in it would otherwise make folders)."""
    if path is None:
        return
    try:
        image_format(path, animated)
    except ValueError as exc:
        raise click.BadParameter(str(exc), param_hint=option) from None
    folder = Path(path).parent
    if not folder.is_dir():
        raise click.BadParameter(f"folder {folder} does not exist", param_hint=option)
