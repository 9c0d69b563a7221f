"""The viewer's materials: the gallery (stored materials, folder materials), uploads, the
uniform builder, and the edits an artist makes. Plain code: no web server in it.

A material is named by an id the page sends back: ``s<store>:<material>`` (a stored
material), ``f<folder>:<k>`` (the k-th material of a ``--materials`` folder), ``up<n>`` (an
upload) or ``uniform:diffuse=#rrggbb;specular=#rrggbb;roughness=X`` (the builder; the
``render_jobs.materials.sources.one_material`` form). Paths never come from the page: an id
can only name what the server listed or stored itself.

Uploads are written to the viewer's own temporary folder only, checked before their images
are decoded (size, pixel count), then read by the loader every other command uses
(``render_jobs.materials``), so a bad upload gets that loader's one-line error.
"""

from __future__ import annotations

import re
import shutil
from collections import OrderedDict
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch

from render_jobs.errors import MaterialError
from render_jobs.materials.files import read_svbrdf_bytes, scan_svbrdf_dir
from render_jobs.materials.maps import srgb_to_linear
from render_jobs.materials.sources import load_map_bytes, one_material
from render_jobs.specs import MaterialSpec, Sun
from storage.reader import Store
from trainer.rendering.mapping import CHANNEL_GROUPS, textures_from_bytes
from trainer.rendering.viewer import MAX_UPLOAD_MB
from trainer.rendering.viewer.recent import Recent

#: the largest upload by default (``trainer viewer --max-upload-mb``)
MAX_UPLOAD_BYTES = MAX_UPLOAD_MB << 20
#: the largest image (pixels)
MAX_PIXELS = 8192 * 8192
#: the most bytes of texture maps kept until the engine takes them (uint8: 10 MB a 1K
#: material, 168 MB a 4K one): an upload's, read to check it, and a gallery picture's
TEXTURE_BYTES = 1 << 30
_SAFE_NAME = re.compile(r"[^A-Za-z0-9._ -]")


@dataclass
class Entry:
    """One material the page can pick. ``suns`` (stored materials only): the light of each
    stored sample, ``{"k", "sample", "azimuth", "elevation", "turbidity"}``."""

    id: str
    label: str
    kind: str
    source: str
    suns: list[dict] = field(default_factory=list)
    spec: MaterialSpec | None = None
    store: int | None = None
    index: int | None = None
    path: Path | None = None

    def to_dict(self) -> dict:
        return {k: getattr(self, k) for k in ("id", "label", "kind", "source", "suns")}


def sun_angles(direction, turbidity: float) -> dict:
    """A sun direction (z up) as the page's azimuth (from +X towards +Y) and elevation."""
    d = np.asarray(direction, np.float64)
    sun = Sun(tuple(float(c) for c in d / np.linalg.norm(d)), float(turbidity))
    return {
        "azimuth": round(sun.azimuth_deg, 3),
        "elevation": round(sun.elevation_deg, 3),
        "turbidity": round(float(turbidity), 3),
    }


def direction(azimuth_deg: float, elevation_deg: float) -> tuple[float, float, float]:
    """The unit sun direction (z up) of the page's angles."""
    az, el = np.radians(azimuth_deg), np.radians(elevation_deg)
    return (float(np.cos(el) * np.cos(az)), float(np.cos(el) * np.sin(az)), float(np.sin(el)))


class Library:
    """The gallery and the uploads of one viewer; ``upload_dir`` is its temporary folder."""

    def __init__(
        self,
        stores: list[str],
        folders: list[str],
        upload_dir: Path,
        max_upload_bytes: int = MAX_UPLOAD_BYTES,
    ):
        self.stores = [Store(u) for u in stores]
        self.upload_dir = upload_dir
        self.max_upload_bytes = max_upload_bytes
        self.entries: OrderedDict[str, Entry] = OrderedDict()
        self._textures = Recent(16, TEXTURE_BYTES)  # material → (10, H, W) uint8 maps
        self.uploads = 0
        for i, store in enumerate(self.stores):
            self._add_store(i, store)
        for j, folder in enumerate(folders):
            for k, path in enumerate(scan_svbrdf_dir(Path(folder))):
                e = Entry(f"f{j}:{k}", path.name, "svbrdf", str(path), path=path)
                self.entries[e.id] = e

    def _add_store(self, i: int, store: Store) -> None:
        lay = store.layout
        materials = store.materials()
        for m, rec in sorted(materials.items()):
            suns = []
            for k in range(lay.suns_per_material):
                sample = m * lay.suns_per_material + k
                d, t = store.light(sample)
                suns.append({"k": k, "sample": sample, **sun_angles(d, t)})
            spec = MaterialSpec.from_dict(rec["spec"]) if rec.get("spec") else None
            label = f"{rec['source_id']} (#{m})"
            e = Entry(f"s{i}:{m}", label, rec["kind"], rec["source_id"], suns, spec, i, m)
            self.entries[e.id] = e

    # ---- what the page lists and picks ------------------------------------------------------

    def listing(self) -> list[dict]:
        return [e.to_dict() for e in self.entries.values()]

    def entry(self, material_id: str) -> Entry:
        """The gallery's or an upload's entry, or a builder material made from its id."""
        e = self.entries.get(material_id)
        if e is not None:
            return e
        if material_id.startswith("uniform:diffuse="):
            spec = one_material(material_id)  # raises MaterialError naming what is wrong
            return Entry(material_id, "uniform", "uniform", material_id, spec=spec)
        raise MaterialError(f"{material_id}: no such material in this viewer")

    def textures(self, material_id: str, keep: bool = True) -> torch.Tensor | None:
        """``(10, H, W) uint8`` texture maps of the material (cached), or ``None`` for a
        stored material whose source cannot be read here (a file on another machine):
        :meth:`stored_maps` then stands in. ``keep=False`` hands them over and removes them from
        this cache: for a caller that keeps them in its own form (the engine's prepared
        textures), so that a material's bytes are held once."""
        cached = self._textures.get(material_id) if keep else self._textures.pop(material_id)
        if cached is not None:
            return cached
        e = self.entry(material_id)
        if e.path is not None:
            maps = read_svbrdf_bytes(e.path)[0]
        elif e.spec is not None:
            try:
                maps = load_map_bytes(e.spec)
            except MaterialError:
                if e.store is None:
                    raise
                return None
        else:
            return None
        tex = textures_from_bytes(maps)
        if keep:
            self._textures.put(material_id, tex)
        return tex

    def stored_maps(self, material_id: str) -> np.ndarray:
        """``(11, R, R) uint8``: a stored material's maps as Cycles' AOVs gave them."""
        e = self.entry(material_id)
        if e.store is None:
            raise MaterialError(f"{material_id}: not a stored material")
        return self.stores[e.store].packed_maps(e.index)

    def truth(self, material_id: str, k: int) -> tuple[np.ndarray, dict]:
        """A stored material's Cycles render under its ``k``-th stored sun: ``(3, R, R)
        float32`` linear HDR, and that sun's angles."""
        e = self.entry(material_id)
        if e.store is None or not 0 <= k < len(e.suns):
            raise MaterialError(f"{material_id}: no stored render {k}")
        sun = e.suns[k]
        return self.stores[e.store].render(sun["sample"]).astype(np.float32), sun

    # ---- uploads ------------------------------------------------------------------------------

    def add_upload(self, files: list[tuple[str, bytes | Path]]) -> Entry:
        """A material from uploaded files, each given as its name and its bytes or a file
        the server received it into (moved here): one 5-panel PNG, or a material's per-map
        images (their names say which map each is, as in material libraries). Raises
        :class:`MaterialError` with one line naming the file; nothing is kept on failure."""
        if not files:
            raise MaterialError("no file uploaded")
        total = sum(d.stat().st_size if isinstance(d, Path) else len(d) for _, d in files)
        if total > self.max_upload_bytes:
            raise MaterialError(
                f"upload of {total / 2**20:.0f} MB is over the viewer's "
                f"{self.max_upload_bytes >> 20} MB limit"
            )
        self.uploads += 1
        folder = self.upload_dir / f"up{self.uploads}"
        folder.mkdir(parents=True)
        try:
            paths = []
            for name, data in files:
                base = _SAFE_NAME.sub("_", Path(name.replace("\\", "/")).name).strip() or "map"
                path = folder / base
                if isinstance(data, Path):
                    shutil.move(data, path)
                else:
                    path.write_bytes(data)
                _check_pixels(path)
                paths.append(path)
            target = paths[0] if len(paths) == 1 else folder
            maps = read_svbrdf_bytes(target)[0]
        except MaterialError as exc:
            shutil.rmtree(folder, ignore_errors=True)
            raise MaterialError(str(exc).replace(str(folder) + "/", "")) from None
        e = Entry(f"up{self.uploads}", Path(files[0][0]).name if len(files) == 1 else
                  f"upload {self.uploads}", "svbrdf", "upload", path=target)  # fmt: skip
        self.entries[e.id] = e
        self._textures.put(e.id, textures_from_bytes(maps))
        return e


def _check_pixels(path: Path) -> None:
    """Refuse an image whose header declares more than ``MAX_PIXELS`` (a small file may
    decode to gigabytes), before anything decodes it."""
    from PIL import Image, UnidentifiedImageError

    try:
        with Image.open(path) as img:
            w, h = img.size
    except (UnidentifiedImageError, OSError):
        return  # not an image PIL knows (EXR, ...): the loader reports it, or reads it
    except Image.DecompressionBombError:  # PIL's own, higher bound: the size is not kept
        w = h = None
    if w is None or w * h > MAX_PIXELS:
        size = f" ({w}x{h})" if w else ""
        raise MaterialError(
            f"{path.name}: the image{size} is over the viewer's limit of {MAX_PIXELS:,} pixels"
        )


@dataclass(frozen=True)
class Edits:
    """An artist's changes to a material, made to its values as the camera sees them: each
    sub-sample's looked-up value, before the pixel filter (``trainer.rendering.mapping``'s
    ``adjust``), so an edit costs the same whatever the size of the texture files.

    ``diffuse_tint``/``specular_tint``: colours (sRGB, in [0, 1]) that multiply the linear
    reflectance; ``diffuse_scale``/``specular_scale``: a factor on top; ``roughness_scale``:
    multiplies roughness; ``normal_strength``: scales the normal map's tilt (0: flat, 1: as it
    is); ``tiling``: repeats the textures that many times as often. Values are clamped to the
    maps' [0, 1]."""

    diffuse_tint: tuple[float, float, float] = (1.0, 1.0, 1.0)
    diffuse_scale: float = 1.0
    specular_tint: tuple[float, float, float] = (1.0, 1.0, 1.0)
    specular_scale: float = 1.0
    roughness_scale: float = 1.0
    normal_strength: float = 1.0
    tiling: float = 1.0

    RANGES = {
        "diffuse_scale": (0.0, 4.0),
        "specular_scale": (0.0, 4.0),
        "roughness_scale": (0.0, 4.0),
        "normal_strength": (0.0, 4.0),
        "tiling": (0.125, 16.0),
    }

    @classmethod
    def from_query(cls, query) -> Edits:
        """From the page's query parameters (absent ones keep their defaults); a value out
        of range or unreadable raises ``ValueError`` naming it."""
        values: dict = {}
        for name in ("diffuse_tint", "specular_tint"):
            if name in query:
                values[name] = hex_colour(query[name], name)
        for name, (lo, hi) in cls.RANGES.items():
            if name in query:
                try:
                    v = float(query[name])
                except ValueError:
                    raise ValueError(f"{name}={query[name]!r} is not a number") from None
                if not lo <= v <= hi:
                    raise ValueError(f"{name}={v:g} is outside [{lo:g}, {hi:g}]")
                values[name] = v
        return cls(**values)

    @property
    def identity(self) -> bool:
        return self == Edits()

    @property
    def changes_values(self) -> bool:
        """Whether :meth:`adjust` changes anything (the tiling is the mapper's)."""
        return self != Edits(tiling=self.tiling)

    def values_of(self, group: str) -> tuple:
        """The values that edit map ``group`` (a key of
        :data:`trainer.rendering.mapping.CHANNEL_GROUPS`)."""
        if group in ("diffuse", "specular"):
            return getattr(self, f"{group}_tint"), getattr(self, f"{group}_scale")
        return (self.roughness_scale,) if group == "roughness" else (self.normal_strength,)

    def groups_changed_from(self, other: Edits) -> list[str]:
        """The maps whose values differ between ``other`` and these edits."""
        return [g for g in CHANNEL_GROUPS if self.values_of(g) != other.values_of(g)]

    def adjust(self, samples: torch.Tensor) -> torch.Tensor:
        """Sub-samples ``(..., 10)`` with these edits, as a new tensor (``samples`` are left
        as they are): linear diffuse and specular, roughness, normal encoded (n + 1) / 2
        (``trainer.rendering.mapping.ScreenMapper.finish``'s ``adjust``). Each map's channels are
        written once: :meth:`edited` for an edited map, a copy for the others."""
        out = torch.empty(samples.shape, dtype=samples.dtype, device=samples.device)
        changed = self.groups_changed_from(Edits())
        for group, channels in CHANNEL_GROUPS.items():
            if group in changed:
                self.edited(group, samples[..., channels], out=out[..., channels])
            else:
                out[..., channels] = samples[..., channels]
        return out

    def edited(
        self, group: str, samples: torch.Tensor, out: torch.Tensor | None = None
    ) -> torch.Tensor:
        """Map ``group``'s channels ``samples (..., k)`` with its edits, in ``out`` or a new
        tensor (``samples`` are left as they are: ``trainer.rendering.mapping.ScreenMapper.
        finish_channels``'s ``edit``). Few torch operations, the gains reckoned in numpy:
        in the viewer, each operation between two frames of the network costs more than
        its arithmetic."""
        if group in ("diffuse", "specular"):
            tint, scale = self.values_of(group)
            gain = torch.from_numpy(srgb_to_linear(np.array(tint, np.float32)) * np.float32(scale))
            return torch.mul(samples, gain.to(samples.device), out=out).clamp_(0.0, 1.0)
        if group == "roughness":
            return torch.mul(samples, self.roughness_scale, out=out).clamp_(0.0, 1.0)
        n = samples * 2.0 - 1.0
        n[..., :2] *= self.normal_strength
        x, y, z = n.unbind(-1)  # the length by components: a reduction over 3 is slower
        length2 = x * x
        length2.addcmul_(y, y).addcmul_(z, z)
        n.mul_(length2.clamp_min_(1e-12).rsqrt_().unsqueeze(-1))
        return torch.clamp(n.add_(1.0).mul_(0.5), 0.0, 1.0, out=out)

    def to_dict(self) -> dict:
        return {k: getattr(self, k) for k in self.__dataclass_fields__}


def hex_colour(text: str, name: str = "colour") -> tuple[float, float, float]:
    """``#rrggbb`` (or ``rrggbb``) → sRGB in [0, 1]; ``ValueError`` naming ``name``."""
    t = text.strip().removeprefix("#")
    if not re.fullmatch(r"[0-9a-fA-F]{6}", t):
        raise ValueError(f"{name}={text!r} is not a #rrggbb colour")
    return tuple(int(t[i : i + 2], 16) / 255 for i in (0, 2, 4))  # type: ignore[return-value]
