"""Labelled contact sheets: the screen maps in one row, the renders below (PIL)."""

from __future__ import annotations

import numpy as np
from PIL import Image, ImageDraw, ImageFont

from render_jobs.materials.maps import linear_to_srgb
from render_jobs.results import ScreenMaps
from render_jobs.tonemap import to_uint8, tonemap


def display_maps(maps: ScreenMaps) -> dict[str, np.ndarray]:
    """Each screen map as a displayable ``(H, W, 3) uint8`` (colours sRGB-encoded)."""
    return {
        "diffuse": to_uint8(linear_to_srgb(maps.diffuse)),
        "specular": to_uint8(linear_to_srgb(maps.specular)),
        "roughness": to_uint8(maps.roughness),
        "normal": to_uint8(maps.normal),
        "mask": to_uint8(maps.mask),
    }


def _label(tile: np.ndarray, text: str, font) -> Image.Image:
    img = Image.fromarray(tile)
    bar = 18 if tile.shape[0] < 256 else 24
    canvas = Image.new("RGB", (img.width, img.height + bar), (24, 24, 24))
    canvas.paste(img, (0, bar))
    ImageDraw.Draw(canvas).text((4, 2), text, fill=(235, 235, 235), font=font)
    return canvas


def contact_sheet(
    maps: ScreenMaps, renders: list[tuple[np.ndarray, str]], title: str = ""
) -> Image.Image:
    """Maps (diffuse, specular, roughness, normal, mask) over renders (radiance, label)."""
    size = maps.mask.shape[-1]
    font = ImageFont.load_default(size=max(10, min(16, size // 16)))
    top = [_label(t, name, font) for name, t in display_maps(maps).items()]
    bottom = [_label(to_uint8(tonemap(r)), text, font) for r, text in renders]
    cols = max(len(top), len(bottom))
    tile_w, tile_h = top[0].width, top[0].height
    head = 28 if title else 0
    sheet = Image.new("RGB", (cols * tile_w, head + 2 * tile_h), (12, 12, 12))
    if title:
        ImageDraw.Draw(sheet).text((6, 6), title, fill=(255, 255, 255), font=font)
    for row, tiles in enumerate((top, bottom)):
        for col, tile in enumerate(tiles):
            sheet.paste(tile, (col * tile_w, head + row * tile_h))
    return sheet
