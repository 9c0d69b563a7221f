"""SVBRDF maps from files, validated: 5-panel PNGs and per-map folders of any library.

A 5-panel PNG (Deschaintre et al. 2018) is W = 5 x H: photo | normal | diffuse | roughness |
specular; the photo is ignored. A per-map folder is read as :mod:`render_jobs.materials.library`
plans it (which file is which map, spec-gloss or metal-rough), then converted here into this
renderer's maps, every step recorded in a :class:`Reading` for ``farm materials``:

- colour maps (diffuse, base colour, specular) in 8/16-bit files are sRGB-encoded, as every
  library ships them; in float files (EXR) they are linear and are encoded here. Data maps
  (roughness, glossiness, metallic, normal) are linear in every format;
- grey maps saved as RGB are read from their (equal) channels; a coloured one is an error;
- glossiness becomes roughness ``1 - g``; a packed ARM/ORM map gives roughness (G) and
  metallic (B); a DirectX normal map gets its green channel flipped (OpenGL, +Y up);
- metal-rough becomes diffuse/specular as glTF 2.0 defines its BRDF (specification, Appendix
  B): ``diffuse = base * (1 - metallic)``, ``specular = lerp(0.04, base, metallic)``, in
  linear colour;
- maps of different sizes are resampled (bilinear) to the largest.

Files are converted a band of rows at a time (:func:`by_bands`): every step above is per
texel, so the maps come out the same, and a 4K material costs its files' bytes and its maps,
not float copies of every file and every step. A material with a float file (EXR) is converted
whole, because its range checks and a normal map's encoding are decided over the whole image.
A folder's files are decoded, and the bands converted, on a few threads (:func:`in_threads`):
the maps are the same whatever the threads, and an error is the one the first culprit in
order gives.

Two readers share this: :func:`read_svbrdf` keeps each band as floats (``MaterialMaps``);
:func:`read_svbrdf_bytes` rounds each band to the 8-bit levels Blender's textures hold
(``MapBytes``) as soon as it is converted, which is what a render worker and the viewer take,
so they never hold a material's float maps.

Every problem raises :class:`MaterialError` as ``"<file or folder>: <problem>"``.
"""

from __future__ import annotations

import functools
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

import render_jobs.materials.images as images
from render_jobs.cpus import omp_threads, usable_cpus
from render_jobs.errors import MaterialError
from render_jobs.materials.library import FolderPlan, looks_like_material, plan_folder
from render_jobs.materials.maps import (
    MAP_CHANNELS,
    MapBytes,
    MaterialMaps,
    check_values,
    linear_to_srgb,
    quantize_u8,
    srgb_table,
)

PANELS = ("photo", "normal", "diffuse", "roughness", "specular")
#: how far a grey map's R, G and B may differ (JPEG noise) before it counts as coloured
GREY_TOLERANCE = 6.0 / 255.0
#: float data maps may overshoot [0, 1] by this much (rounding) and are clipped
FLOAT_SLACK = 1e-3
DIELECTRIC_F0 = 0.04
#: texels converted at a time: a band's float temporaries stay small (3 MB for RGB, within
#: a shared cache with a few threads at work)
BAND_PIXELS = 1 << 18
#: threads that decode a folder's files and convert bands side by side (at most; fewer on
#: fewer CPUs, :func:`_cpus`), each holding one band's temporaries
MAX_THREADS = 4


@dataclass
class Reading:
    """How one material was read: for the dry run and the errors."""

    source: str
    workflow: str  # "5-panel", "spec-gloss" or "metal-rough"
    files: dict[str, str] = field(default_factory=dict)  # map -> file name (and how)
    conversions: list[str] = field(default_factory=list)
    ignored: list[tuple[str, str]] = field(default_factory=list)


def _stored(img: images.Image) -> np.ndarray:
    """The samples of an image taken as they are: 8-bit ones as stored, which the band's
    ``finish`` turns into what ``Image.rows`` gives (:func:`floats`) or keeps as the 8-bit
    levels they are (:func:`levels`); others as ``Image.rows`` floats."""
    return img.data if img.bits == 8 else img.rows()


def _colour(img: images.Image, name: str) -> np.ndarray:
    """A colour map as sRGB-encoded ``(H, W, 3)`` (:func:`_stored` samples, or floats)."""
    px = _rgb(img.pixels if img.is_float else _stored(img))
    if img.is_float:
        _check_range(img, px, name)
        px = linear_to_srgb(np.clip(px, 0.0, 1.0))
    return px


def _linear_colour(img: images.Image, name: str) -> np.ndarray:
    """A colour map as linear ``(H, W, 3)``: a float file's values (linear by convention),
    integer samples decoded from sRGB by ``srgb_table`` (the curve's values, by one gather)."""
    if img.is_float:
        px = img.pixels
        _check_range(img, px, name)
        px = np.clip(px, 0.0, 1.0)
    else:
        px = srgb_table(img.bits)[img.data]
    return np.ascontiguousarray(_rgb(px), dtype=np.float32)


def _rgb(px: np.ndarray) -> np.ndarray:
    """``(H, W, C)`` samples as RGB: a grey channel repeated, an alpha channel dropped."""
    return np.repeat(px, 3, axis=2) if px.shape[2] == 1 else px[..., :3]


def _check_range(img: images.Image, px: np.ndarray, name: str) -> None:
    lo, hi = float(px.min()), float(px.max())
    if lo < -FLOAT_SLACK or hi > 1.0 + FLOAT_SLACK:
        raise MaterialError(
            f"{img.path}: {name} map values must lie in [0, 1], got [{lo:.3g}, {hi:.3g}]"
        )


def _grey(img: images.Image, name: str, stored: bool = False) -> np.ndarray:
    """A grey map as ``(H, W, 1)`` in [0, 1]; with ``stored``, a one-channel 8-bit file's
    :func:`_stored` samples."""
    if stored and img.channels == 1 and img.bits == 8:
        return _stored(img)
    px = img.pixels
    if px.shape[2] >= 3:
        rgb = px[..., :3]
        grey = rgb.mean(axis=2, keepdims=True)
        if np.abs(rgb - grey).max() > GREY_TOLERANCE:
            raise MaterialError(f"{img.path}: {name} map is not greyscale (its R, G, B differ)")
        px = grey
    if img.is_float:
        _check_range(img, px, name)
    return np.ascontiguousarray(np.clip(px, 0.0, 1.0), dtype=np.float32)


def _normal(img: images.Image, stored: bool = False) -> np.ndarray:
    """A normal map as ``(H, W, 3)`` encoded (n + 1) / 2; with ``stored``, an 8-bit file's
    :func:`_stored` samples (else floats of its own, which the caller may change)."""
    if img.channels < 3:
        raise MaterialError(f"{img.path}: normal map must have 3 channels (RGB), got 1")
    if stored and img.bits == 8:
        return _stored(img)[..., :3]
    px = img.pixels
    px = px[..., :3]
    if img.is_float and px.min() < -FLOAT_SLACK:  # stored as vectors in [-1, 1]
        px = (px + 1.0) * 0.5
    if img.is_float:
        _check_range(img, px, "normal")
    return np.ascontiguousarray(np.clip(px, 0.0, 1.0), dtype=np.float32)


def _resize(img: images.Image, size: tuple[int, int]) -> images.Image:
    """``img`` resampled to ``size`` (bilinear, OpenCV) in its stored sample type: an 8-bit
    map stays 8-bit, rounded as the same map stored at that size would be, and no float copy
    of it is made (an 8K set: 201 MB an RGB map, not 805)."""
    import cv2

    out = cv2.resize(np.ascontiguousarray(img.data), (size[1], size[0]),
                     interpolation=cv2.INTER_LINEAR)  # fmt: skip
    return images.Image(img.path, out.reshape(size[0], size[1], img.channels), img.bits)


def load_panel_png(path: Path, finish) -> dict[str, np.ndarray]:
    """A Deschaintre-style 5-panel PNG as maps (:func:`by_bands` with ``finish``)."""
    img = images.read(path)
    h, w = img.size
    if w != 5 * h:
        raise MaterialError(
            f"{path}: expected 5 square panels side by side (width = 5 x height), "
            f"got {w}x{h} ({w / h:.2f} panels)"
        )
    if img.channels not in (3, 4):
        raise MaterialError(f"{path}: expected an RGB image, got {img.channels} channel(s)")

    def convert(start: int, stop: int) -> dict[str, np.ndarray]:
        band = img.band(start, stop)  # the photo panel is never converted
        panel = {name: images.Image(path, band.data[:, i * h : (i + 1) * h, :3], img.bits)
                 for i, name in enumerate(PANELS)}  # fmt: skip
        return {
            "diffuse": _stored(panel["diffuse"]),
            "specular": _stored(panel["specular"]),
            "roughness": _grey(panel["roughness"], "roughness panel"),
            "normal": _stored(panel["normal"]),
        }

    return by_bands((h, h), band_rows(img.size, [img]), convert, finish)


def band_rows(size: tuple[int, int], imgs) -> int:
    """Rows a band of images of ``size`` (height, width): about :data:`BAND_PIXELS` texels,
    or every row when an image is float."""
    if any(img.is_float for img in imgs):
        return size[0]
    return max(1, BAND_PIXELS // size[1])


def by_bands(size: tuple[int, int], rows: int, convert, finish) -> dict[str, np.ndarray]:
    """Maps of ``size`` (height, width), made ``rows`` rows at a time by ``convert(start, stop)``
    (name to ``(stop - start, width, C)`` floats, or 8-bit samples taken as they are:
    :func:`_stored`), each band kept as ``finish(name, band)`` gives it (:func:`floats` or
    :func:`levels`). The first band sizes the maps; the others
    are converted by :func:`in_threads` (``convert`` reads its inputs only; each band writes
    its own rows)."""
    first = {k: finish(k, v) for k, v in convert(0, min(rows, size[0])).items()}
    if rows >= size[0]:
        return first
    out: dict[str, np.ndarray] = {}
    for name, band in first.items():
        out[name] = np.empty((*size, band.shape[2]), band.dtype)
        out[name][:rows] = band
    del first

    def put(start: int) -> None:
        stop = min(start + rows, size[0])
        for name, band in convert(start, stop).items():
            out[name][start:stop] = finish(name, band)

    in_threads(put, list(range(rows, size[0], rows)))
    return out


def floats(name: str, band: np.ndarray) -> np.ndarray:
    """A converted band kept as ``float32`` (:class:`MaterialMaps` checks the whole maps);
    8-bit samples scaled to [0, 1] as ``Image.rows`` scales them."""
    if band.dtype == np.uint8:
        return images.scaled(band)
    return np.ascontiguousarray(band, np.float32)


def levels(where: str, name: str, band: np.ndarray) -> np.ndarray:
    """A converted band kept as :class:`MapBytes` keeps it: 8-bit samples as they are (the
    levels their floats round to), floats checked as :class:`MaterialMaps` checks a map (an
    error names ``where``) and rounded to 8 bits (``quantize_u8``)."""
    if band.dtype == np.uint8:
        return np.ascontiguousarray(band)
    check_values(where, name, band)
    return quantize_u8(band)


def in_threads(fn, items: list, threads: int | None = None) -> list:
    """``[fn(x) for x in items]`` on ``threads`` threads (by default :data:`MAX_THREADS` or the
    process's CPUs, fewer): OpenCV's decoders and numpy's array loops release the GIL. Results
    in order; an error raises as the first failing item's, in order, and the items not
    started then are dropped."""
    threads = min(threads or min(MAX_THREADS, _cpus()), len(items))
    if threads <= 1:
        return [fn(x) for x in items]
    with ThreadPoolExecutor(threads, thread_name_prefix="material-read") as pool:
        return list(pool.map(fn, items))


def _cpus() -> int:
    """The CPUs this process may use (``render_jobs.cpus.usable_cpus``), at most
    ``OMP_NUM_THREADS`` when that is set (``omp_threads``: so a farm worker reads on its own
    share)."""
    cpus = usable_cpus()
    return min(cpus, omp_threads() or cpus)


def read_map_folder(folder: Path, finish) -> tuple[dict[str, np.ndarray], Reading]:
    """A per-map folder as maps (:func:`by_bands` with ``finish``), and how it was read."""
    plan = plan_folder(folder)
    reading = Reading(str(folder), plan.workflow, ignored=list(plan.ignored))
    reading.conversions.extend(plan.notes)
    roles, paths = list(plan.files), list(plan.files.values())
    imgs = dict(zip(roles, in_threads(images.read, paths), strict=True))
    size = max((img.size for img in imgs.values()), key=lambda s: s[0] * s[1])
    for role, img in imgs.items():
        reading.files[role] = f"{img.path.name} ({img.describe()})"
        if img.size != size:
            reading.conversions.append(
                f"{img.path.name} resampled from {img.size[1]}x{img.size[0]} to {size[1]}x{size[0]}"
            )
            imgs[role] = _resize(img, size)
    packed = imgs.get("packed")
    if packed is not None and packed.channels < 3:
        raise MaterialError(f"{packed.path}: a packed ARM/ORM map needs 3 channels")

    def convert(start: int, stop: int) -> dict[str, np.ndarray]:
        band = {role: img.band(start, stop) for role, img in imgs.items()}
        return _convert(plan, band, (stop - start, size[1]))

    maps = by_bands(size, band_rows(size, imgs.values()), convert, finish)
    reading.conversions.extend(_notes(plan, imgs))
    return maps, reading


def _notes(plan: FolderPlan, imgs: dict) -> list[str]:
    """What :func:`_convert` does to the plan's images, in its order, for the dry run."""
    notes = []
    if plan.roughness_from == "packed":
        notes.append(f"roughness from the green channel of {imgs['packed'].path.name}")
    elif plan.roughness_from == "glossiness":
        notes.append("roughness = 1 - glossiness")
    if "normal" in imgs and plan.normal_from == "normal_dx":
        notes.append("DirectX normal map: green flipped to OpenGL")
    elif "normal" in imgs and plan.normal_from == "normal":
        notes.append("normal map taken as OpenGL (its name does not say)")
    if plan.workflow == "metal-rough":
        if plan.metallic_from == "packed":
            notes.append(f"metallic from the blue channel of {imgs['packed'].path.name}")
        notes.append(
            "metal-rough to diffuse/specular (glTF 2.0): diffuse = base x (1 - metallic), "
            "specular = lerp(0.04, base, metallic)"
        )
    return notes


def _convert(plan: FolderPlan, imgs: dict, size: tuple[int, int]) -> dict:
    """The plan's images (or the same rows of each) as this renderer's four maps."""
    packed = imgs["packed"].pixels if "packed" in imgs else None  # once, for both its maps
    if plan.roughness_from == "packed":
        rough = np.clip(packed[..., 1:2], 0.0, 1.0)
    elif plan.roughness_from == "glossiness":
        rough = 1.0 - _grey(imgs["glossiness"], "glossiness")
    else:
        rough = _grey(imgs["roughness"], "roughness", stored=True)
    if "normal" in imgs:
        flip = plan.normal_from == "normal_dx"
        normal = _normal(imgs["normal"], stored=not flip)
        if flip:  # _normal's array is its own
            normal[..., 1] = 1.0 - normal[..., 1]
    else:
        normal = np.broadcast_to(np.array([0.5, 0.5, 1.0], np.float32), (*size, 3))
    if plan.workflow == "spec-gloss":
        diffuse = _colour(imgs["diffuse"], "diffuse")
        specular = _colour(imgs["specular"], "specular")
    else:
        diffuse, specular = _metal_rough(plan, imgs, size, packed)
    return {"diffuse": diffuse, "specular": specular, "roughness": rough, "normal": normal}


def _metal_rough(plan: FolderPlan, imgs: dict, size: tuple[int, int], packed: np.ndarray | None):
    base = _linear_colour(imgs["basecolor"], "base colour")
    if plan.metallic_from == "packed":
        metal = np.clip(packed[..., 2:3], 0.0, 1.0)
    elif plan.metallic_from == "metallic":
        metal = _grey(imgs["metallic"], "metallic")
    else:
        metal = np.zeros((*size, 1), np.float32)
    diffuse, specular = metal_rough_to_spec_gloss(base, metal)
    return linear_to_srgb(diffuse), linear_to_srgb(specular)


def metal_rough_to_spec_gloss(base: np.ndarray, metallic: np.ndarray):
    """Linear base colour ``(..., 3)`` and metallic ``(..., 1)`` → linear (diffuse,
    specular), as glTF 2.0 (Appendix B) mixes its dielectric and metal BRDFs."""
    # metallic repeated to 3 channels: numpy's broadcast of a last axis of 1 is a few times
    # slower than the plain elementwise loop, which gives the same values
    metallic = np.repeat(np.asarray(metallic, np.float32), base.shape[-1], axis=-1)
    dielectric = 1.0 - metallic
    diffuse = base * dielectric
    specular = DIELECTRIC_F0 * dielectric
    specular += base * metallic
    return diffuse.astype(np.float32, copy=False), specular.astype(np.float32, copy=False)


def read_svbrdf(path: Path) -> tuple[MaterialMaps, Reading]:
    """A 5-panel image file or a per-map folder, and how it was read."""
    maps, reading = _read(Path(path), floats)
    return MaterialMaps(**maps, source_id=Path(path).name), reading


def read_svbrdf_bytes(path: Path) -> tuple[MapBytes, Reading]:
    """:func:`read_svbrdf` as the 8-bit textures Blender and the viewer's mapper take:
    ``MapBytes.of(read_svbrdf(path)[0])`` bit for bit, read without the float maps (a 4K
    material holds 160 MB of maps, not 640), refused as :class:`MaterialMaps` refuses."""
    name = Path(path).name
    maps, reading = _read(Path(path), functools.partial(levels, name))
    return MapBytes({k: maps[k] for k in MAP_CHANNELS}, name), reading


def _read(path: Path, finish) -> tuple[dict[str, np.ndarray], Reading]:
    if path.is_dir():
        if not looks_like_material(path) and any(
            p.suffix.lower() == ".png" for p in path.iterdir()
        ):
            raise MaterialError(
                f"{path}: a folder of materials (5-panel PNGs), not one material; "
                "name one file, or give the folder to farm submit / farm materials"
            )
        return read_map_folder(path, finish)
    if not path.exists():
        raise MaterialError(f"{path}: file not found")
    maps = load_panel_png(path, finish)
    return maps, Reading(str(path), "5-panel", files={"panels": path.name})


def scan_svbrdf_dir(folder: Path) -> list[Path]:
    """The materials under ``folder``, sorted.

    A per-map folder (:func:`library.looks_like_material`) is one material; otherwise every
    ``.png`` in it is a 5-panel material and every per-map sub-folder is one material. A file
    is itself.
    """
    if not folder.exists():
        raise MaterialError(f"{folder}: no such directory")
    if not folder.is_dir():
        return [folder]
    if looks_like_material(folder):
        return [folder]
    entries = [
        p
        for p in sorted(folder.iterdir())
        if (p.is_file() and p.suffix.lower() == ".png") or (p.is_dir() and looks_like_material(p))
    ]
    if not entries:
        raise MaterialError(
            f"{folder}: no materials found (expected 5-panel PNGs or folders of per-map images)"
        )
    return entries
