"""Schema version 1 of the shard store: every array's name, shape, dtype and chunking, the
layout, the commit records' keys, one shard's data, and the map encoding.

This module is the one statement of the format: the writer creates and checks arrays from
:func:`arrays`, the readers and ``shards verify`` check them against it.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, field

import numpy as np
from numcodecs import BitRound

from render_jobs.materials.maps import linear_to_srgb, quantize_u8, srgb_to_linear
from render_jobs.specs import MATERIAL_KINDS

SCHEMA_VERSION = 1
ATTRS_KEY = "shaderball"
COMMITS = "commits"
MAP_CHANNELS = {"diffuse": 3, "specular": 3, "roughness": 1, "normal": 3, "mask": 1}
PACKED_CHANNELS = sum(MAP_CHANNELS.values())  # 11: the maps of one material, packed
KINDS = MATERIAL_KINDS
#: a store's image side must be a multiple of this for the trainer's U-Net, which halves
#: the image four times; the store itself takes any side of 8 or more
TRAINABLE_MULTIPLE = 16
PER_SAMPLE = {  # name: (trailing shape, dtype)
    "material_index": ((), "int32"),
    "sun_direction": ((3,), "float32"),
    "turbidity": ((), "float32"),
    "seed": ((), "int64"),
    "render_seconds": ((), "float32"),
}


def untrainable(resolution: int, nearest: bool = True) -> str | None:
    """Why the trainer cannot learn from images ``resolution`` pixels a side, with (if
    ``nearest``) the nearest sides it can; ``None`` when it can."""
    m = TRAINABLE_MULTIPLE
    if resolution >= m and resolution % m == 0:
        return None
    positive = "" if resolution > 0 else "positive "
    why = (
        f"resolution {resolution} is not a {positive}multiple of {m}, which the trainer's "
        "U-Net needs (it halves the image four times)"
    )
    if not nearest:
        return why
    lower, upper = max(m, resolution // m * m), (resolution // m + 1) * m
    return f"{why}: try {lower} or {upper}" if lower < resolution else f"{why}: try {upper}"


@dataclass(frozen=True)
class Layout:
    """Counts and sizes that fix every array's shape and every shard's extent."""

    num_materials: int
    suns_per_material: int
    resolution: int
    shard_size: int  # samples per shard

    def __post_init__(self) -> None:
        if self.num_materials < 1 or self.suns_per_material < 1 or self.resolution < 8:
            raise ValueError(f"invalid layout {self}")
        if self.shard_size < 1 or self.shard_size % self.suns_per_material:
            raise ValueError(
                f"shard size ({self.shard_size}) must be a positive multiple of the suns per "
                f"material ({self.suns_per_material}), so a material's suns share a shard"
            )

    @property
    def num_samples(self) -> int:
        return self.num_materials * self.suns_per_material

    @property
    def materials_per_shard(self) -> int:
        return self.shard_size // self.suns_per_material

    @property
    def num_shards(self) -> int:
        return -(-self.num_samples // self.shard_size)

    def shard_samples(self, shard: int) -> range:
        """Sample indices of ``shard``."""
        self._check_shard(shard)
        return range(shard * self.shard_size, min((shard + 1) * self.shard_size, self.num_samples))

    def shard_materials(self, shard: int) -> range:
        """Material indices of ``shard``."""
        self._check_shard(shard)
        m = self.materials_per_shard
        return range(shard * m, min((shard + 1) * m, self.num_materials))

    def shard_of_sample(self, sample: int) -> int:
        self._check_sample(sample)
        return sample // self.shard_size

    def material_of_sample(self, sample: int) -> int:
        self._check_sample(sample)
        return sample // self.suns_per_material

    def _check_sample(self, sample: int) -> None:
        if not 0 <= sample < self.num_samples:
            raise IndexError(f"sample {sample} out of range (store has {self.num_samples})")

    def check_material(self, material: int) -> None:
        """An ``IndexError`` naming ``material`` when the store has no such material."""
        if not 0 <= material < self.num_materials:
            raise IndexError(f"material {material} out of range (store has {self.num_materials})")

    def _check_shard(self, shard: int) -> None:
        if not 0 <= shard < self.num_shards:
            raise IndexError(f"shard {shard} out of range (store has {self.num_shards})")

    def to_dict(self) -> dict:
        return asdict(self)


@dataclass(frozen=True)
class ArraySpec:
    """One array of the store: ``shape`` (whole store), ``dtype``, ``chunks`` (one read unit),
    ``shards`` (one file; ``None``: one chunk a shard), and the shape of one shard's part."""

    shape: tuple
    dtype: str
    chunks: tuple
    shards: tuple | None
    per_material: bool  # indexed by material (maps), else by sample

    def part(self, count: int) -> tuple:
        """The shape of ``count`` materials' or samples' rows of it."""
        return (count, *self.shape[1:])


def arrays(layout: Layout) -> dict[str, ArraySpec]:
    """Every array of a store with ``layout``, by name."""
    r, m, n, s = layout.resolution, layout.num_materials, layout.num_samples, layout.shard_size
    mps = layout.materials_per_shard
    packed = (PACKED_CHANNELS, r, r)
    out = {
        "maps": ArraySpec((m, *packed), "uint8", (1, *packed), (mps, *packed), True),
        "renders": ArraySpec((n, 3, r, r), "float16", (1, 3, r, r), (s, 3, r, r), False),
    }
    for name, (tail, dtype) in PER_SAMPLE.items():
        out[name] = ArraySpec((n, *tail), dtype, (s, *tail), None, False)
    return out


def commit_key(shard: int) -> str:
    return f"{COMMITS}/{shard:06d}.json"


@dataclass
class ShardPayload:
    """One shard's data, as ``write_shard`` takes it and ``Store.read_shard`` returns it: an
    attribute per array of :func:`arrays`, each holding the shard's rows. ``maps`` ``(m, 11, H,
    W) uint8`` (:func:`encode_maps`); ``renders`` ``(n, 3, H, W)`` float16 linear HDR; per
    sample ``material_index (n,) int32``, ``sun_direction (n, 3)``, ``turbidity (n,)``, ``seed
    (n,) int64``, ``render_seconds (n,)``. ``materials``: one dict per material (``kind``,
    ``source_id``, ``spec``)."""

    maps: np.ndarray
    renders: np.ndarray
    material_index: np.ndarray
    sun_direction: np.ndarray
    turbidity: np.ndarray
    seed: np.ndarray
    render_seconds: np.ndarray
    materials: list[dict] = field(default_factory=list)


def encode_maps(maps: dict[str, np.ndarray]) -> np.ndarray:
    """Screen maps (float32 ``(C, H, W)`` each, colours linear) → ``(11, H, W) uint8``."""
    parts = []
    for name, channels in MAP_CHANNELS.items():
        arr = np.asarray(maps[name], dtype=np.float32)
        if arr.shape[0] != channels:
            raise ValueError(f"{name} map has {arr.shape[0]} channels, expected {channels}")
        if name in ("diffuse", "specular"):
            arr = linear_to_srgb(arr)
        parts.append(arr)
    return quantize_u8(np.concatenate(parts))


#: the store setting (in its attributes' ``settings``) that keeps this many of float16's 10
#: mantissa bits in every render; a store without it keeps all 10
RENDER_BITS = "render_bits"
FLOAT16_MANTISSA_BITS = 10


def round_renders(renders: np.ndarray, bits: int) -> np.ndarray:
    """``(n, 3, H, W) float16`` renders with ``bits`` of their 10 mantissa bits kept, each
    rounded to the nearest (ties to even; numcodecs' ``BitRound``). The bits dropped are
    zeros, which zstd packs: fewer bytes a render for a relative error of at most
    2^-(bits+1) (of a normal value; a subnormal one, under 6.1e-5, has fewer bits to keep
    and may round to 0). A value that would round past float16's largest is rounded down."""
    if bits >= FLOAT16_MANTISSA_BITS:
        return renders
    renders = np.ascontiguousarray(renders, dtype=np.float16)
    rounded = BitRound(keepbits=bits).encode(renders).view(np.float16)
    mask = np.uint16((0xFFFF << (FLOAT16_MANTISSA_BITS - bits)) & 0xFFFF)
    down = (renders.view(np.uint16) & mask).view(np.float16)
    return np.where(np.isinf(rounded) & np.isfinite(renders), down, rounded)


def decode_maps(packed: np.ndarray) -> dict[str, np.ndarray]:
    """``(11, H, W) uint8`` → screen maps (float32 ``(C, H, W)``, colours linear)."""
    x = packed.astype(np.float32) / 255.0
    out, start = {}, 0
    for name, channels in MAP_CHANNELS.items():
        part = x[start : start + channels]
        out[name] = srgb_to_linear(part) if name in ("diffuse", "specular") else part
        start += channels
    return out
