"""Several stores read as one dataset, and the held-out split by material."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from storage.errors import StoreError
from storage.reader import Sample, ShardStore


@dataclass(frozen=True)
class SampleRef:
    store: int  # index into Dataset.stores
    sample: int  # index inside that store


class Dataset:
    """The committed samples of several stores, indexed 0..len-1 store after store."""

    def __init__(self, stores: list[ShardStore]):
        if not stores:
            raise StoreError("a dataset needs at least one store")
        res = {s.layout.resolution for s in stores}
        if len(res) != 1:
            raise StoreError(f"stores have different resolutions {sorted(res)}")
        self.stores = stores
        self.refs: list[SampleRef] = []
        for i, store in enumerate(stores):
            for shard in store.committed_shards():
                self.refs += [SampleRef(i, s) for s in store.layout.shard_samples(shard)]

    @classmethod
    def open(cls, urls: list[str], storage_options: dict | None = None) -> Dataset:
        return cls([ShardStore(u, storage_options) for u in urls])

    def __len__(self) -> int:
        return len(self.refs)

    def __getitem__(self, index: int) -> Sample:
        if not 0 <= index < len(self.refs):
            raise IndexError(f"sample {index} out of range (dataset has {len(self.refs)})")
        ref = self.refs[index]
        return self.stores[ref.store].sample(ref.sample)

    def material_of(self, index: int) -> tuple[int, int]:
        """(store, material) of dataset sample ``index``: the unit of the held-out split."""
        ref = self.refs[index]
        return ref.store, self.stores[ref.store].layout.material_of_sample(ref.sample)


def split_by_material(
    dataset: Dataset, seed: int, holdout: int | None = None, fraction: float | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """(train, test) dataset indices; the test set holds ``holdout`` materials (or a
    ``fraction`` of them), drawn by ``seed``, with all their suns: no material straddles."""
    if (holdout is None) == (fraction is None):
        raise ValueError("give exactly one of holdout or fraction")
    materials = sorted({dataset.material_of(i) for i in range(len(dataset))})
    count = holdout if holdout is not None else round(fraction * len(materials))
    if not 0 <= count <= len(materials):
        raise ValueError(f"cannot hold out {count} of {len(materials)} materials")
    order = np.random.default_rng(seed).permutation(len(materials))
    held = {materials[i] for i in order[:count]}
    test = np.array([i for i in range(len(dataset)) if dataset.material_of(i) in held], np.int64)
    train = np.setdiff1d(np.arange(len(dataset)), test)
    return train, test
