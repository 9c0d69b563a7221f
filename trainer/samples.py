"""Reading a split's samples into batches of tensors, and naming a set of them.

A :class:`storage.catalog.Split` names samples across stores; :class:`SampleReader` reads
any of them as the network's batches (training's stream, held-out scores, evaluation), and
:func:`samples_digest` names a set of them so that two runs' scores can be told to be of the
same samples.
"""

from __future__ import annotations

import hashlib
import json

import numpy as np
import torch

from storage.catalog import Split
from storage.reader import Store
from trainer.targets import light_vector


class SampleReader:
    """Reads samples of a split into batches; opens its stores on first use (per process)."""

    def __init__(self, split: Split):
        self.split = split
        self._stores: list[Store] | None = None

    def __getstate__(self):
        return {"split": self.split, "_stores": None}

    @property
    def stores(self) -> list[Store]:
        if self._stores is None:
            self._stores = [Store(u, self.split.storage_options) for u in self.split.urls]
        return self._stores

    def batch(self, ids: np.ndarray) -> dict[str, torch.Tensor]:
        """Samples ``ids`` → ``maps (B, 11, H, W) uint8``, ``render (B, 3, H, W) float16``
        (linear HDR), ``light (B, 4) float32``, ``id (B,) int64``."""
        maps, renders, lights = [], [], []
        for i in ids:
            s, k = self.split.refs[i]
            store = self.stores[s]
            renders.append(store.render(int(k)))
            maps.append(store.packed_maps(store.layout.material_of_sample(int(k))))
            lights.append(light_vector(*store.light(int(k))))
        return {
            "maps": torch.from_numpy(np.stack(maps)),
            "render": torch.from_numpy(np.stack(renders)),
            "light": torch.from_numpy(np.stack(lights)),
            "id": torch.as_tensor(np.asarray(ids, np.int64)),
        }


def samples_digest(split: Split, ids: np.ndarray) -> str:
    """A short name of the samples ``ids`` of ``split`` (their stores and sample numbers):
    two runs whose held-out scores carry the same one scored the same samples."""
    h = hashlib.sha256(json.dumps(list(split.urls)).encode())
    h.update(np.ascontiguousarray(split.refs[ids], dtype=np.int64).tobytes())
    return h.hexdigest()[:12]
