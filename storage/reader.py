"""Reading a store: random access by sample, iteration by committed shard.

Only committed shards are visible: a sample whose shard has no commit record is refused.
Random access reads chunks directly (``storage.chunks``), caching per-shard indexes, the
small per-sample arrays of each shard, and the last few materials' maps (5 suns share them);
whole-shard reads (``read_shard``, used by ``shards verify``) go through zarr itself.
"""

from __future__ import annotations

import json
from dataclasses import dataclass

import numpy as np

from render_jobs.screen_uv import FILE, ScreenUV, ScreenUVError
from render_jobs.specs import Sun
from storage.backend import Backend
from storage.chunks import ChunkReader
from storage.errors import StoreError
from storage.retry import retrying
from storage.schema import (
    ATTRS_KEY,
    COMMITS,
    PER_SAMPLE,
    SCHEMA_VERSION,
    Layout,
    ShardPayload,
    arrays,
    commit_key,
    decode_maps,
)


@dataclass
class Sample:
    """One training pair: ``render`` ``(3, H, W) float32`` linear HDR; ``maps`` as
    ``storage.schema.decode_maps`` returns them (float32 ``(C, H, W)``, colours linear)."""

    index: int
    render: np.ndarray
    maps: dict[str, np.ndarray]
    material_index: int
    sun: Sun
    seed: int
    render_seconds: float
    kind: str
    source_id: str


class Store:
    """An opened store (local path or ``s3://`` URL)."""

    #: bytes of packed material maps kept in memory (about 54 materials at 400²): a material's
    #: suns share its maps, and shuffled reads come back to it
    maps_cache_bytes = 96 << 20

    def __init__(self, url: str, storage_options: dict | None = None):
        self.url = str(url)
        self.backend = Backend(url, storage_options)
        raw = self.backend.get("zarr.json")
        if raw is None:
            raise StoreError(f"{url}: not a shard store (no zarr.json)")
        try:
            meta = json.loads(raw)
        except json.JSONDecodeError:
            raise StoreError(f"{url}: zarr.json is not valid JSON") from None
        attrs = meta.get("attributes", {}).get(ATTRS_KEY)
        if meta.get("node_type") != "group" or not isinstance(attrs, dict):
            raise StoreError(f"{url}: a zarr store, but not a shaderball shard store")
        version = attrs.get("schema_version")
        if version != SCHEMA_VERSION:
            raise StoreError(
                f"{url}: unknown schema version {version!r} "
                f"(this shaderball reads {SCHEMA_VERSION})"
            )
        self.attrs = attrs
        self.layout = Layout(**attrs["layout"])
        self.settings: dict = attrs.get("settings", {})
        self._group = None
        self._known: dict[int, dict] = {}  # commit records seen, by shard
        self._meta: dict[int, dict[str, np.ndarray]] = {}
        self._readers: dict[str, ChunkReader] = {}
        self._maps_cache: dict[int, np.ndarray] = {}

    # ---- metadata -------------------------------------------------------------------------

    @property
    def group(self):
        if self._group is None:
            self._group = self.backend.open_group(mode="r")
        return self._group

    def check_compatible(self, layout: Layout, settings: dict) -> None:
        """Raise naming the first field where ``layout``/``settings`` differ from the store's."""
        for name, ours, theirs in [
            *((f"layout.{k}", v, getattr(self.layout, k)) for k, v in layout.to_dict().items()),
            *((f"settings.{k}", v, self.settings.get(k)) for k, v in settings.items()),
        ]:
            if json.loads(json.dumps(ours)) != theirs:
                raise StoreError(
                    f"{self.url}: the store was made with {name}={theirs!r}, not {ours!r}"
                )

    def commit_record(self, shard: int) -> dict | None:
        raw = self.backend.get(commit_key(shard))
        if raw is None:
            return None
        try:
            return json.loads(raw)
        except json.JSONDecodeError:
            raise StoreError(f"{self.url}: commit record of shard {shard} is corrupt") from None

    def commits(self) -> dict[int, dict]:
        """Every commit record, by shard."""
        out = {}
        for name in self.backend.listdir(COMMITS):
            if name.endswith(".json") and not name.startswith("."):
                shard = int(name.removesuffix(".json"))
                rec = self.commit_record(shard)
                if rec is not None:
                    out[shard] = rec
        return out

    def committed_shards(self) -> list[int]:
        return sorted(self.commits())

    def shard_keys(self, shard: int) -> list[str]:
        """The object keys holding ``shard`` (one per array)."""
        return [
            f"{name}/c/" + "/".join([str(shard)] + ["0"] * (len(spec.shape) - 1))
            for name, spec in arrays(self.layout).items()
        ]

    def shard_state(self, shard: int, commits: dict[int, dict] | None = None) -> str:
        """``committed``, ``pending`` (bytes but no commit record) or ``empty``."""
        commits = self.commits() if commits is None else commits
        if shard in commits:
            return "committed"
        if any(self.backend.size(k) for k in self.shard_keys(shard)):
            return "pending"
        return "empty"

    def shard_bytes(self, shard: int) -> int:
        return sum(self.backend.size(k) or 0 for k in self.shard_keys(shard))

    def screen_uv(self):
        """The store's :class:`render_jobs.screen_uv.ScreenUV` (``None`` when it has none);
        raises :class:`StoreError` when it is unreadable or does not fit the store."""

        raw = self.backend.get(FILE)
        if raw is None:
            return None
        try:
            suv = ScreenUV.from_bytes(raw, f"{self.url}/{FILE}")
            suv.check_fits({**self.settings, "resolution": self.layout.resolution}, self.url)
        except ScreenUVError as exc:
            raise StoreError(str(exc)) from None
        return suv

    def materials(self, commits: dict[int, dict] | None = None) -> dict[int, dict]:
        """Committed materials' records (``kind``, ``source_id``, ``spec``), by index (of
        ``commits``, the store's :meth:`commits`, read now when not given)."""
        commits = self.commits() if commits is None else commits
        return {m["index"]: m for rec in commits.values() for m in rec["materials"]}

    # ---- data -----------------------------------------------------------------------------

    def _require_committed(self, sample: int) -> tuple[int, dict]:
        shard = self.layout.shard_of_sample(sample)
        rec = self._known.get(shard)
        if rec is None:  # commits only ever appear: look again only on a miss
            rec = self.commit_record(shard)
            if rec is not None:
                self._known[shard] = rec
        if rec is None:
            raise StoreError(f"{self.url}: sample {sample} is in shard {shard}, not committed")
        return shard, rec

    @retrying
    def array(self, name: str):
        """The zarr array ``name`` (its metadata read now); ``KeyError`` if it is missing."""
        return self.group[name]

    @retrying
    def _read_rows(self, shard: int, names) -> dict[str, np.ndarray]:
        """The rows of ``shard`` in the arrays ``names``, through zarr."""
        lay, g, specs = self.layout, self.group, arrays(self.layout)
        out = {}
        for name in names:
            per_material = specs[name].per_material
            rows = lay.shard_materials(shard) if per_material else lay.shard_samples(shard)
            out[name] = g[name][rows.start : rows.stop]
        return out

    def forget(self, shard: int) -> None:
        """Drop what is cached of ``shard`` (its commit record, metadata, maps): it is being
        rewritten."""
        self._known.pop(shard, None)
        self._meta.pop(shard, None)
        self._maps_cache.clear()

    def _shard_meta(self, shard: int) -> dict[str, np.ndarray]:
        """The small per-sample arrays of a committed shard (read once, then cached)."""
        meta = self._meta.get(shard)
        if meta is None:
            meta = self._read_rows(shard, PER_SAMPLE)
            self._meta[shard] = meta
            if len(self._meta) > 512:
                self._meta.pop(next(iter(self._meta)))
        return meta

    def _chunks(self, name: str):
        reader = self._readers.get(name)
        if reader is None:
            reader = self._readers[name] = ChunkReader(self.backend, name)
        return reader

    def render(self, index: int) -> np.ndarray:
        """Sample ``index``'s render: ``(3, H, W) float16`` linear HDR (no copy, read-only)."""
        shard, _ = self._require_committed(index)
        return self._chunks("renders").chunk(shard, index - shard * self.layout.shard_size)[0]

    def packed_maps(self, material: int) -> np.ndarray:
        """Material ``material``'s maps as stored: ``(11, H, W) uint8`` (read-only)."""
        cached = self._maps_cache.get(material)
        if cached is not None:
            return cached
        self.layout.check_material(material)
        shard = material // self.layout.materials_per_shard
        self._require_committed(shard * self.layout.shard_size)
        k = material - shard * self.layout.materials_per_shard
        packed = self._chunks("maps").chunk(shard, k)[0]
        self._maps_cache[material] = packed
        while len(self._maps_cache) * packed.nbytes > self.maps_cache_bytes:
            self._maps_cache.pop(next(iter(self._maps_cache)))
        return packed

    def light(self, index: int) -> tuple[np.ndarray, float]:
        """Sample ``index``'s sun: ``(3,) float32`` unit direction (z up) and turbidity."""
        shard, _ = self._require_committed(index)
        meta = self._shard_meta(shard)
        j = index - shard * self.layout.shard_size
        d = meta["sun_direction"][j].astype(np.float32)
        return d / np.linalg.norm(d), float(meta["turbidity"][j])

    def sample(self, index: int) -> Sample:
        """Sample ``index`` with its material's maps and its light."""
        try:
            shard, rec = self._require_committed(index)
        except IndexError as exc:
            raise StoreError(f"{self.url}: {exc}") from None
        material = self.layout.material_of_sample(index)
        info = next(m for m in rec["materials"] if m["index"] == material)
        meta = self._shard_meta(shard)
        j = index - shard * self.layout.shard_size
        d = meta["sun_direction"][j].astype(np.float64)
        return Sample(
            index=index,
            render=self.render(index).astype(np.float32),
            maps=decode_maps(self.packed_maps(material)),
            material_index=material,
            sun=Sun(tuple(float(c) for c in d / np.linalg.norm(d)), float(meta["turbidity"][j])),
            seed=int(meta["seed"][j]),
            render_seconds=float(meta["render_seconds"][j]),
            kind=info["kind"],
            source_id=info["source_id"],
        )

    def read_shard(self, shard: int):
        """The whole of a committed ``shard`` as a :class:`storage.schema.ShardPayload`."""
        rec = self.commit_record(shard)
        if rec is None:
            raise StoreError(f"{self.url}: shard {shard} is not committed")
        rows = self._read_rows(shard, arrays(self.layout))
        materials = [{k: v for k, v in r.items() if k != "index"} for r in rec["materials"]]
        return ShardPayload(materials=materials, **rows)
