"""SVBRDF maps from files, validated: 5-panel PNGs and folders of per-map images.

A 5-panel PNG (Deschaintre et al. 2018) is W = 5 x H: photo | normal | diffuse | roughness |
specular; the photo is ignored. A folder holds one file per map, found by name: diffuse
(``diffuse``, ``basecolor``, ``base_color``, ``albedo``), ``specular``, ``roughness``, ``normal``.
Images must be 8-bit (PNG, JPEG, TIFF, BMP, TGA) or 32-bit float TIFF with values in [0, 1].
Every problem raises :class:`MaterialError` as ``"<file>: <problem>"``.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
from PIL import Image, UnidentifiedImageError

from render_jobs.errors import MaterialError
from render_jobs.materials.maps import MaterialMaps

IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".tif", ".tiff", ".bmp", ".tga")
PANELS = ("photo", "normal", "diffuse", "roughness", "specular")
MAP_NAME_TOKENS = {
    "diffuse": ("diffuse", "basecolor", "base_color", "albedo"),
    "specular": ("specular",),
    "roughness": ("roughness",),
    "normal": ("normal",),
}
_GREY_TOLERANCE = 2.0 / 255.0


def read_image(path: Path) -> np.ndarray:
    """An image file as ``(H, W, C) float32`` in [0, 1] (C = 1, 3 or 4)."""
    try:
        with Image.open(path) as img:
            img.load()
            mode = img.mode
            if mode.startswith("I;16") or mode == "I":
                raise MaterialError(f"{path}: 16-bit images are not supported (save it as 8-bit)")
            if mode == "P":
                img = img.convert("RGBA" if "transparency" in img.info else "RGB")
                mode = img.mode
            if mode == "1":
                img = img.convert("L")
                mode = "L"
            if mode == "F":
                arr = np.asarray(img, dtype=np.float32)[..., None]
                if not np.all(np.isfinite(arr)):
                    raise MaterialError(f"{path}: holds NaN or Inf values")
                if arr.min() < 0.0 or arr.max() > 1.0:
                    raise MaterialError(
                        f"{path}: float values must lie in [0, 1], "
                        f"got [{arr.min():.3g}, {arr.max():.3g}]"
                    )
                return arr
            if mode not in ("L", "LA", "RGB", "RGBA"):
                raise MaterialError(f"{path}: unsupported image mode {mode!r} (use 8-bit RGB)")
            arr = np.asarray(img, dtype=np.uint8)
    except FileNotFoundError:
        raise MaterialError(f"{path}: file not found") from None
    except (UnidentifiedImageError, OSError, SyntaxError, ValueError) as exc:
        if isinstance(exc, MaterialError):
            raise
        raise MaterialError(f"{path}: not a readable image ({exc})") from None
    if arr.ndim == 2:
        arr = arr[..., None]
    if arr.shape[0] == 0 or arr.shape[1] == 0:
        raise MaterialError(f"{path}: image is empty")
    return arr.astype(np.float32) / 255.0


def _colour(arr: np.ndarray, path: Path, name: str) -> np.ndarray:
    c = arr.shape[2]
    if c in (3, 4):
        return np.ascontiguousarray(arr[..., :3])
    if c == 1:
        return np.repeat(arr, 3, axis=2)
    raise MaterialError(f"{path}: {name} map must have 1, 3 or 4 channels, got {c}")


def _normal(arr: np.ndarray, path: Path) -> np.ndarray:
    if arr.shape[2] not in (3, 4):
        raise MaterialError(f"{path}: normal map must have 3 channels (RGB), got {arr.shape[2]}")
    return np.ascontiguousarray(arr[..., :3])


def _grey(arr: np.ndarray, path: Path, name: str) -> np.ndarray:
    c = arr.shape[2]
    if c == 1:
        return arr
    if c not in (3, 4):
        raise MaterialError(f"{path}: {name} map must have 1 or 3 channels, got {c}")
    rgb = arr[..., :3]
    if np.abs(rgb - rgb[..., :1]).max() > _GREY_TOLERANCE:
        raise MaterialError(f"{path}: {name} map is not greyscale (its R, G, B differ)")
    return np.ascontiguousarray(rgb[..., :1])


def load_panel_png(path: Path) -> MaterialMaps:
    """A Deschaintre-style 5-panel PNG as maps."""
    arr = read_image(path)
    h, w, c = arr.shape
    if w != 5 * h:
        panels = w / h
        raise MaterialError(
            f"{path}: expected 5 square panels side by side (width = 5 x height), "
            f"got {w}x{h} ({panels:.2f} panels)"
        )
    if c not in (3, 4):
        raise MaterialError(f"{path}: expected an RGB image, got {c} channel(s)")
    panel = {name: arr[:, i * h : (i + 1) * h, :3] for i, name in enumerate(PANELS)}
    return MaterialMaps(
        diffuse=np.ascontiguousarray(panel["diffuse"]),
        specular=np.ascontiguousarray(panel["specular"]),
        roughness=_grey(panel["roughness"], path, "roughness panel of"),
        normal=np.ascontiguousarray(panel["normal"]),
        source_id=path.name,
    )


def find_map_files(folder: Path) -> dict[str, Path]:
    """The file of each map in ``folder``, by name; raises when one is missing or ambiguous."""
    files = sorted(
        p for p in folder.iterdir() if p.is_file() and p.suffix.lower() in IMAGE_SUFFIXES
    )
    found: dict[str, Path] = {}
    for name, tokens in MAP_NAME_TOKENS.items():
        hits = [p for p in files if any(t in p.stem.lower() for t in tokens)]
        if not hits:
            raise MaterialError(
                f"{folder}: no {name} map (expected an image whose name contains "
                f"{' or '.join(repr(t) for t in tokens)})"
            )
        if len(hits) > 1:
            names = ", ".join(p.name for p in hits)
            raise MaterialError(f"{folder}: ambiguous {name} map: {names}")
        found[name] = hits[0]
    return found


def load_map_folder(folder: Path) -> MaterialMaps:
    """A folder of per-map images as maps (all maps must share one size)."""
    paths = find_map_files(folder)
    arrays = {name: read_image(p) for name, p in paths.items()}
    ref_name = "diffuse"
    ref = arrays[ref_name].shape[:2]
    for name, arr in arrays.items():
        if arr.shape[:2] != ref:
            raise MaterialError(
                f"{paths[name]}: mismatched sizes: {name} is {arr.shape[1]}x{arr.shape[0]} "
                f"but {ref_name} is {ref[1]}x{ref[0]}"
            )
    return MaterialMaps(
        diffuse=_colour(arrays["diffuse"], paths["diffuse"], "diffuse"),
        specular=_colour(arrays["specular"], paths["specular"], "specular"),
        roughness=_grey(arrays["roughness"], paths["roughness"], "roughness"),
        normal=_normal(arrays["normal"], paths["normal"]),
        source_id=folder.name,
    )


def load_svbrdf(path: Path) -> MaterialMaps:
    """A 5-panel image file or a per-map folder."""
    if path.is_dir():
        return load_map_folder(path)
    if not path.exists():
        raise MaterialError(f"{path}: file not found")
    return load_panel_png(path)


def looks_like_map_folder(folder: Path) -> bool:
    """True when the image names in ``folder`` name at least two different maps."""
    stems = [
        p.stem.lower()
        for p in folder.iterdir()
        if p.is_file() and p.suffix.lower() in IMAGE_SUFFIXES
    ]
    kinds = {
        name for name, tokens in MAP_NAME_TOKENS.items() for t in tokens for s in stems if t in s
    }
    return len(kinds) >= 2


def scan_svbrdf_dir(folder: Path) -> list[Path]:
    """The materials under ``folder``, sorted.

    A per-map folder (``looks_like_map_folder``) is one material; otherwise every ``.png`` in
    it is a 5-panel material and every per-map sub-folder is one material. A file is itself.
    """
    if not folder.exists():
        raise MaterialError(f"{folder}: no such directory")
    if not folder.is_dir():
        return [folder]
    if looks_like_map_folder(folder):
        return [folder]
    entries = []
    for p in sorted(folder.iterdir()):
        if (p.is_file() and p.suffix.lower() == ".png") or (
            p.is_dir() and looks_like_map_folder(p)
        ):
            entries.append(p)
    if not entries:
        raise MaterialError(
            f"{folder}: no materials found (expected 5-panel PNGs or folders of per-map images)"
        )
    return entries
