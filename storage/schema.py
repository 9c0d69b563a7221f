"""Schema version 1 of the shard store: arrays, dtypes, layout, and map encoding."""

from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np

from render_jobs.materials.maps import linear_to_srgb, srgb_to_linear

SCHEMA_VERSION = 1
ATTRS_KEY = "shaderball"
COMMITS = "commits"
MAP_CHANNELS = {"diffuse": 3, "specular": 3, "roughness": 1, "normal": 3, "mask": 1}
MAPS_CHANNELS = sum(MAP_CHANNELS.values())  # 11
KINDS = ("uniform", "procedural", "svbrdf")
PER_SAMPLE = {  # name: (trailing shape, dtype)
    "material_index": ((), "int32"),
    "sun_direction": ((3,), "float32"),
    "turbidity": ((), "float32"),
    "seed": ((), "int64"),
    "render_seconds": ((), "float32"),
}


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
        if not 0 <= sample < self.num_samples:
            raise IndexError(f"sample {sample} out of range (store has {self.num_samples})")
        return sample // self.shard_size

    def material_of_sample(self, sample: int) -> int:
        return sample // self.suns_per_material

    def _check_shard(self, shard: int) -> None:
        if not 0 <= shard < self.num_shards:
            raise IndexError(f"shard {shard} out of range (store has {self.num_shards})")

    def to_dict(self) -> dict:
        return asdict(self)


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
    return (np.clip(np.concatenate(parts), 0.0, 1.0) * 255.0 + 0.5).astype(np.uint8)


def decode_maps(packed: np.ndarray) -> dict[str, np.ndarray]:
    """``(11, H, W) uint8`` → screen maps (float32 ``(C, H, W)``, colours linear)."""
    x = packed.astype(np.float32) / 255.0
    out, start = {}, 0
    for name, channels in MAP_CHANNELS.items():
        part = x[start : start + channels]
        out[name] = srgb_to_linear(part) if name in ("diffuse", "specular") else part
        start += channels
    return out
