"""Results waiting for their shard: a shard is written once all its materials are rendered.

Plain data, no Ray: the driver adds each material's result and gets a shard's results back, in
material order, when the last one arrives. A material that failed for good kills its shard
(left uncommitted, rendered again on resume), and results for a dead shard are dropped.
"""

from __future__ import annotations

from storage.schema import Layout


class ShardAssembly:
    def __init__(self, layout: Layout):
        self.layout = layout
        self.waiting: dict[int, dict[int, dict]] = {}
        self.dead: set[int] = set()

    def shard_of(self, material: int) -> int:
        return material // self.layout.materials_per_shard

    def add(self, material: int, result: dict) -> tuple[int, list[dict]] | None:
        """Keep ``result``; ``(shard, results in material order)`` once the shard is whole."""
        shard = self.shard_of(material)
        if shard in self.dead:
            return None
        got = self.waiting.setdefault(shard, {})
        got[material] = result
        members = self.layout.shard_materials(shard)
        if len(got) < len(members):
            return None
        del self.waiting[shard]
        return shard, [got[m] for m in members]

    def keep(self, shard: int, results: dict[int, object]) -> None:
        """Put back the ``results`` (by material) of ``shard`` whose commit failed: what
        survived waits again for the materials rendered anew."""
        self.waiting.setdefault(shard, {}).update(results)

    def kill(self, material: int) -> int:
        """``material`` failed for good: its shard will not be written."""
        shard = self.shard_of(material)
        self.dead.add(shard)
        self.waiting.pop(shard, None)
        return shard
