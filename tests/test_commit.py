"""A shard committed by a commit task (``farm.commit``), without Ray: the function itself."""

from __future__ import annotations

import numpy as np

from farm.commit import commit_shard, placement
from storage.reader import Store
from storage.schema import Layout
from storage.verify import verify
from storage.writer import create_store
from tests.flaky_proxy import FlakyProxy
from tests.storage_helpers import synthetic_payload
from tests.test_storage_flaky import flaky_options

LAYOUT = Layout(num_materials=4, suns_per_material=2, resolution=16, shard_size=4)


def packed_results(shard: int) -> tuple[list[dict], list[dict]]:
    """A shard's materials as render workers return them, and their records."""
    p = synthetic_payload(LAYOUT, shard)
    k = LAYOUT.suns_per_material
    packed = [
        {
            "maps": p.maps[j],
            "renders": p.renders[j * k : (j + 1) * k],
            "sun_direction": p.sun_direction[j * k : (j + 1) * k],
            "turbidity": p.turbidity[j * k : (j + 1) * k],
            "seed": p.seed[j * k : (j + 1) * k],
            "seconds": p.render_seconds[j * k : (j + 1) * k],
        }
        for j in range(len(p.maps))
    ]
    return packed, p.materials


def test_a_commit_writes_the_shard_and_a_rerun_reports_it_instead_of_failing(tmp_path):
    url = str(tmp_path / "s.zarr")
    create_store(url, LAYOUT, {})
    packed, records = packed_results(1)
    first = commit_shard(url, None, 1, records, *packed)
    assert first["shard"] == 1 and not first["again"] and first["bytes"] > 0
    assert first["retries"] == []
    store = Store(url)
    assert store.committed_shards() == [1]
    np.testing.assert_array_equal(store.group["maps"][2:4], np.stack([p["maps"] for p in packed]))
    # Ray re-runs a task whose process died after the commit record was put
    again = commit_shard(url, None, 1, records, *packed)
    assert again["again"] and again["bytes"] == first["bytes"]
    assert store.committed_shards() == [1]


def test_a_commit_over_a_flaky_object_store_reports_its_retries(s3):
    endpoint, opts = s3
    url = "s3://shaderball/commit-task.zarr"
    create_store(url, LAYOUT, {}, storage_options=opts)
    packed, records = packed_results(0)
    with FlakyProxy.past_client_retries(endpoint, every=6, method="PUT") as proxy:
        report = commit_shard(url, flaky_options(opts, proxy.endpoint), 0, records, *packed)
    assert sum(proxy.faults.values()) > 0
    assert report["retries"] and all("retry" in line for line in report["retries"])
    assert Store(url, opts).committed_shards() == [0]
    assert verify(Store(url, opts)).ok


def test_local_stores_are_written_on_the_drivers_machine_object_stores_anywhere():
    assert placement("out/x.zarr") == "driver" and placement("file:///data/x.zarr") == "driver"
    assert placement("s3://bucket/x.zarr") == "anywhere"
