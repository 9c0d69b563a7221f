"""Several stores as one training set, split by material: a snapshot kept with a run.

A :class:`Catalog` is a snapshot of one or more stores (local or ``s3://``): the committed
shards of each and the held-out materials, fixed when a run starts and kept in its
checkpoints, so a store that grows while training (a farm still running) changes neither the
order of a resumed epoch nor the split. Whole materials (all their suns) are held out, so no
material straddles the split. :meth:`Catalog.split` gives the ``train`` or ``test`` samples as
``(store, sample)`` references grouped by shard, which the trainer streams.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from storage.errors import StoreError
from storage.reader import Store


def draw_heldout(materials: list, count: int, seed: int) -> list:
    """``count`` of ``materials`` (a sorted list of any keys), drawn by ``seed``."""
    if not 0 <= count <= len(materials):
        raise ValueError(f"cannot hold out {count} of {len(materials)} materials")
    order = np.random.default_rng(seed).permutation(len(materials))
    return [materials[i] for i in order[:count]]


def holdout_count(fraction: float, materials: list) -> int:
    """How many of ``materials`` to hold out: ``fraction`` of them, at least one when there
    are two or more, and never all of them."""
    count = round(fraction * len(materials))
    if fraction > 0 and len(materials) > 1:
        count = max(count, 1)
    return max(0, min(count, len(materials) - 1))


def identities(stores: list[Store], commits: list[dict]) -> dict[str, list[tuple[int, int]]]:
    """Each committed material's ``source_id`` → its copies, as ``(store, material)``
    (``store`` an index into ``stores``; ``commits`` each store's :meth:`Store.commits`)."""
    copies: dict[str, list[tuple[int, int]]] = {}
    for i, (s, committed) in enumerate(zip(stores, commits, strict=True)):
        records = s.materials(committed)
        for shard in sorted(committed):
            for m in s.layout.shard_materials(shard):
                copies.setdefault(records[m]["source_id"], []).append((i, m))
    return copies


@dataclass
class Catalog:
    """Stores, their committed shards and held-out materials, as of one moment."""

    urls: list[str]
    shards: list[list[int]]  # committed shards per store
    heldout: list[list[int]]  # held-out material indices per store
    resolution: int
    # the ``source_id`` of every material the network trains on (with those of the run it
    # is fine-tuned from) and of every one it holds out; ``None`` in a catalog that does not
    # name them (a checkpoint's from an older shaderball: read from its stores)
    trained_sources: list[str] | None = None
    held_sources: list[str] | None = None
    # materials found more than once (by ``source_id``) when the snapshot was taken; not kept
    repeated: int = field(default=0, compare=False)

    @classmethod
    def snapshot(
        cls,
        urls: list[str],
        seed: int,
        holdout_fraction: float,
        storage_options: dict | None,
        keep: tuple[set[str], set[str]] | None = None,
    ) -> Catalog:
        """Open ``urls`` and draw the held-out materials: ``holdout_fraction`` of them (at
        least one when there are two or more), by ``seed``.

        Materials are drawn by identity (``source_id``), so a material in several stores
        (rendered again, or by two farm jobs with the same ``--seed``) is on one side of the
        split in all of them, and the draw does not depend on the order of ``urls``.
        ``keep`` (a fine-tuned run's: the ``source_id`` of each material the run it starts
        from trained on, and of each it held out) keeps those materials on their side, in
        whichever store they are: held out stay held out, trained on stay in training. Only
        the others are drawn, at ``holdout_fraction``."""
        if not 0 <= holdout_fraction < 1:
            raise ValueError(f"holdout fraction must be in [0, 1), not {holdout_fraction}")
        stores = [Store(u, storage_options) for u in urls]
        commits = [s.commits() for s in stores]  # read once: a farm may be committing more
        for s, committed in zip(stores, commits, strict=True):
            if not committed:
                raise StoreError(f"{s.url}: the store has no committed samples to train on")
        copies = identities(stores, commits)
        trained, kept = keep or (set(), set())
        unseen = sorted(copies.keys() - trained - kept)
        held = kept | set(draw_heldout(unseen, holdout_count(holdout_fraction, unseen), seed))
        heldout: list[set[int]] = [set() for _ in urls]
        for source in held & copies.keys():
            for store, material in copies[source]:
                heldout[store].add(material)
        return cls(
            urls=[s.url for s in stores],
            shards=[sorted(c) for c in commits],
            heldout=[sorted(h) for h in heldout],
            resolution=stores[0].layout.resolution,
            trained_sources=sorted(trained | (copies.keys() - held)),
            held_sources=sorted(held),
            repeated=sum(len(c) > 1 for c in copies.values()),
        )

    @property
    def records_sources(self) -> bool:
        """Whether the catalog names its materials itself (:meth:`material_sources` then
        reads no store)."""
        return self.trained_sources is not None

    def material_sources(self, stores: list[Store] | None = None) -> tuple[set[str], set[str]]:
        """The ``source_id`` of every material the snapshot trains on and of every one it
        holds out: as recorded, or for a catalog kept without them read from its stores
        opened where they are now (``stores``, in order; at its ``urls`` when not given)."""
        if self.records_sources:
            return set(self.trained_sources), set(self.held_sources)
        stores = [Store(u) for u in self.urls] if stores is None else stores
        trained, held = set(), set()
        for store, shards, heldout in zip(stores, self.shards, self.heldout, strict=True):
            records = store.materials()
            for shard in shards:
                for m in store.layout.shard_materials(shard):
                    (held if m in heldout else trained).add(records[m]["source_id"])
        return trained, held

    def to_dict(self) -> dict:
        return {
            "urls": list(self.urls),
            "shards": [list(s) for s in self.shards],
            "heldout": [list(h) for h in self.heldout],
            "resolution": self.resolution,
            "trained_sources": self.trained_sources,
            "held_sources": self.held_sources,
        }

    @classmethod
    def from_dict(cls, d: dict) -> Catalog:
        return cls(**d)

    def split(self, which: str, storage_options: dict | None = None) -> Split:
        """The ``train`` or ``test`` (held-out) samples, or ``all``, grouped by shard."""
        if which not in ("train", "test", "all"):
            raise ValueError(f"split must be train, test or all, not {which!r}")
        refs, groups = [], []
        for s, url in enumerate(self.urls):
            layout = Store(url, storage_options).layout
            held = set(self.heldout[s])
            for shard in self.shards[s]:
                ids = [
                    k
                    for k in layout.shard_samples(shard)
                    if which == "all" or (layout.material_of_sample(k) in held) == (which == "test")
                ]
                if ids:
                    groups.append(np.arange(len(refs), len(refs) + len(ids)))
                    refs += [(s, k) for k in ids]
        return Split(self.urls, np.array(refs, np.int64).reshape(-1, 2), groups, storage_options)


@dataclass
class Split:
    """Samples of a catalog: ``refs (N, 2) int64`` = (store, sample), ``groups`` = ids by shard."""

    urls: list[str]
    refs: np.ndarray
    groups: list[np.ndarray]
    storage_options: dict | None = None

    def __len__(self) -> int:
        return len(self.refs)
