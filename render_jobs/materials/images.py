"""Reading texture files as they come from material libraries: 8- and 16-bit PNG, JPEG, TIFF
(8-, 16-bit and float), BMP, TGA and OpenEXR.

An :class:`Image` keeps the samples as stored (``uint8``, ``uint16`` or ``float32``) and gives
``float32`` rows on demand: integer samples scaled to [0, 1] by their bit depth, float ones
(EXR, float TIFF) as stored, which must be finite. Keeping the stored samples lets a reader
convert a large image a band of rows at a time (:mod:`render_jobs.materials.files`), so a 4K
map costs its bytes plus one band of floats, not a float copy of the whole image.

Which values are colour (sRGB) and which are data is not decided here but by the map each file
is (:mod:`render_jobs.materials.library`): :class:`Image` says whether the file held floats,
since a float colour map is linear by convention (EXR).

OpenCV reads PNG, JPEG, TIFF and BMP (Pillow reads 16-bit RGB PNG as 8 bits); Pillow reads
TGA; the ``OpenEXR`` package reads EXR. Every problem raises :class:`MaterialError` as
``"<file>: <problem>"``.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from render_jobs.errors import MaterialError

SUFFIXES = (".png", ".jpg", ".jpeg", ".tif", ".tiff", ".bmp", ".tga", ".exr")
#: refuse images above this many pixels (a 16k x 16k map), before decoding them
MAX_PIXELS = 16384 * 16384


@dataclass(frozen=True)
class Image:
    """``data``: ``(H, W, C)``, C = 1, 3 or 4, as stored (``uint8``, ``uint16``) or as floats
    (``float32``: a float file, or an image already converted); ``bits``: the file's 8, 16
    or 32 (float); ``is_float``: stored as floats (linear by convention)."""

    path: Path
    data: np.ndarray
    bits: int

    @property
    def is_float(self) -> bool:
        return self.bits == 32

    @property
    def size(self) -> tuple[int, int]:
        """(height, width)."""
        return self.data.shape[0], self.data.shape[1]

    @property
    def channels(self) -> int:
        return self.data.shape[2]

    def rows(self, start: int = 0, stop: int | None = None) -> np.ndarray:
        """Rows ``start:stop`` as ``float32``: integers scaled to [0, 1], floats as they are."""
        band = self.data[start:stop]
        return scaled(band) if band.dtype in (np.uint8, np.uint16) else band

    def band(self, start: int, stop: int) -> Image:
        """The same image's rows ``start:stop`` (a view of its samples)."""
        return Image(self.path, self.data[start:stop], self.bits)

    @property
    def pixels(self) -> np.ndarray:
        """The whole image as ``float32`` (:meth:`rows`)."""
        return self.rows()

    def describe(self) -> str:
        h, w = self.size
        kind = "float" if self.is_float else f"{self.bits}-bit"
        return f"{w}x{h} {kind}, {self.channels} channel(s)"


def scaled(samples: np.ndarray) -> np.ndarray:
    """8- or 16-bit samples as ``float32`` in [0, 1] (``v / 255`` or ``v / 65535``)."""
    out = samples.astype(np.float32)
    out /= 255.0 if samples.dtype == np.uint8 else 65535.0  # in place: no second copy
    return out


def read(path: Path) -> Image:
    """The image at ``path``; raises :class:`MaterialError` naming it on any problem."""
    path = Path(path)
    if not path.is_file():
        raise MaterialError(f"{path}: file not found")
    suffix = path.suffix.lower()
    if suffix == ".exr":
        pixels, bits = _read_exr(path)
    elif suffix == ".tga":
        pixels, bits = _read_pillow(path)
    else:
        pixels, bits = _read_cv2(path)
    if pixels.ndim == 2:
        pixels = pixels[..., None]
    if pixels.shape[0] == 0 or pixels.shape[1] == 0:
        raise MaterialError(f"{path}: image is empty")
    if pixels.shape[2] not in (1, 2, 3, 4):
        raise MaterialError(f"{path}: {pixels.shape[2]} channels (expected 1 to 4)")
    if pixels.shape[2] == 2:  # grey + alpha
        pixels = pixels[..., :1]
    if bits == 32:
        pixels = pixels.astype(np.float32, copy=False)
        if not np.all(np.isfinite(pixels)):
            raise MaterialError(f"{path}: holds NaN or Inf values")
    return Image(path, np.ascontiguousarray(pixels), bits)


def _read_cv2(path: Path) -> tuple[np.ndarray, int]:
    import cv2

    data = np.fromfile(path, dtype=np.uint8)  # cv2.imread cannot say why it failed
    arr = cv2.imdecode(data, cv2.IMREAD_UNCHANGED) if data.size else None
    if arr is None:
        raise MaterialError(f"{path}: not a readable image (truncated or not an image file)")
    if arr.shape[0] * arr.shape[1] > MAX_PIXELS:
        raise MaterialError(f"{path}: {arr.shape[1]}x{arr.shape[0]} is too large")
    if arr.ndim == 3 and arr.shape[2] >= 3:  # OpenCV keeps BGR(A)
        arr = _rgb(arr)
    if arr.dtype in (np.uint8, np.uint16):
        return arr, 8 if arr.dtype == np.uint8 else 16
    if arr.dtype in (np.float32, np.float64, np.float16):
        return arr.astype(np.float32, copy=False), 32
    raise MaterialError(f"{path}: unsupported sample type {arr.dtype} (use 8/16-bit or float)")


def _rgb(arr: np.ndarray) -> np.ndarray:
    """OpenCV's BGR(A) as RGB(A), in place by ``cvtColor`` for the types it takes (a few times
    faster than an indexed copy, and no second image), an indexed copy for the others."""
    import cv2

    if arr.shape[2] in (3, 4) and arr.dtype in (np.uint8, np.uint16, np.float32):
        code = cv2.COLOR_BGR2RGB if arr.shape[2] == 3 else cv2.COLOR_BGRA2RGBA
        return cv2.cvtColor(arr, code, dst=arr)
    return arr[..., [2, 1, 0, *range(3, arr.shape[2])]]


def _read_pillow(path: Path) -> tuple[np.ndarray, int]:
    from PIL import Image as PILImage
    from PIL import UnidentifiedImageError

    try:
        with PILImage.open(path) as img:
            img.load()
            if img.mode not in ("L", "LA", "RGB", "RGBA"):
                img = img.convert("RGBA" if "A" in img.getbands() else "RGB")
            arr = np.asarray(img, dtype=np.uint8)
    except (UnidentifiedImageError, OSError, SyntaxError, ValueError) as exc:
        raise MaterialError(f"{path}: not a readable image ({exc})") from None
    return arr, 8


def _read_exr(path: Path) -> tuple[np.ndarray, int]:
    import OpenEXR

    try:
        with OpenEXR.File(str(path), separate_channels=True) as f:
            channels = {name: np.asarray(ch.pixels) for name, ch in f.channels().items()}
    except Exception as exc:  # noqa: BLE001 - the OpenEXR binding raises plain exceptions
        raise MaterialError(f"{path}: not a readable EXR ({str(exc).splitlines()[0]})") from None
    names = {n.split(".")[-1].upper(): n for n in channels}
    if all(c in names for c in "RGB"):
        order = ["R", "G", "B", *(["A"] if "A" in names else [])]
    elif "Y" in names:
        order = ["Y"]
    elif len(names) == 1:  # one channel of any name is a grey map
        order = list(names)
    else:
        raise MaterialError(f"{path}: has channels {sorted(channels)}, expected RGB(A) or Y")
    arr = np.stack([channels[names[c]] for c in order], axis=-1)
    return arr.astype(np.float32), 32
