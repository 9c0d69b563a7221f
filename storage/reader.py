"""Reading a store: random access by sample, iteration by committed shard.

Only committed shards are visible: a sample whose shard has no commit record is refused.
"""

from __future__ import annotations

import json
from collections.abc import Iterator
from dataclasses import dataclass

import numpy as np

from render_jobs.specs import Sun
from storage.backend import Backend
from storage.errors import StoreError
from storage.schema import ATTRS_KEY, COMMITS, PER_SAMPLE, SCHEMA_VERSION, Layout, decode_maps

ARRAYS = ("maps", "renders", *PER_SAMPLE)


def commit_key(shard: int) -> str:
    return f"{COMMITS}/{shard:06d}.json"


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


class ShardStore:
    """An opened store (local path or ``s3://`` URL)."""

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
        keys = []
        for name in ARRAYS:
            ndim = 4 if name in ("maps", "renders") else 1 + len(PER_SAMPLE[name][0])
            keys.append(f"{name}/c/" + "/".join([str(shard)] + ["0"] * (ndim - 1)))
        return keys

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

    def materials(self) -> dict[int, dict]:
        """Committed materials' records (``kind``, ``source_id``, ``spec``), by index."""
        return {m["index"]: m for rec in self.commits().values() for m in rec["materials"]}

    # ---- data -----------------------------------------------------------------------------

    def _require_committed(self, sample: int) -> tuple[int, dict]:
        shard = self.layout.shard_of_sample(sample)
        rec = self.commit_record(shard)
        if rec is None:
            raise StoreError(f"{self.url}: sample {sample} is in shard {shard}, not committed")
        return shard, rec

    def sample(self, index: int) -> Sample:
        """Sample ``index`` with its material's maps and its light."""
        try:
            _, rec = self._require_committed(index)
        except IndexError as exc:
            raise StoreError(f"{self.url}: {exc}") from None
        g = self.group
        material = self.layout.material_of_sample(index)
        info = next(m for m in rec["materials"] if m["index"] == material)
        d = g["sun_direction"][index]
        return Sample(
            index=index,
            render=g["renders"][index].astype(np.float32),
            maps=decode_maps(g["maps"][material]),
            material_index=material,
            sun=Sun(tuple(float(c) for c in d / np.linalg.norm(d)), float(g["turbidity"][index])),
            seed=int(g["seed"][index]),
            render_seconds=float(g["render_seconds"][index]),
            kind=info["kind"],
            source_id=info["source_id"],
        )

    def read_shard(self, shard: int):
        """The whole of a committed ``shard`` as a :class:`storage.writer.ShardPayload`."""
        from storage.writer import ShardPayload

        rec = self.commit_record(shard)
        if rec is None:
            raise StoreError(f"{self.url}: shard {shard} is not committed")
        g = self.group
        s, m = self.layout.shard_samples(shard), self.layout.shard_materials(shard)
        per = {name: g[name][s.start : s.stop] for name in PER_SAMPLE}
        return ShardPayload(
            maps=g["maps"][m.start : m.stop],
            renders=g["renders"][s.start : s.stop],
            materials=[{k: v for k, v in r.items() if k != "index"} for r in rec["materials"]],
            **per,
        )

    def iter_shards(self) -> Iterator[tuple[int, object]]:
        """(shard, payload) for every committed shard, in order."""
        for shard in self.committed_shards():
            yield shard, self.read_shard(shard)
