"""A store of real Blender renders: what the farm will write, read back faithfully."""

from __future__ import annotations

import numpy as np
import pytest

from render_jobs.materials import load_maps, specs_from_sources
from render_jobs.specs import derive_seed
from render_jobs.sun import sample_suns
from storage.convert import payload_from_renders
from storage.schema import Layout
from storage.writer import create_store, write_shard
from tests.conftest import TINY

pytestmark = pytest.mark.slow


def test_rendered_store_round_trip(worker, tmp_path):
    specs = specs_from_sources(["uniform:2", "procedural:2"], dataset_seed=0)
    layout = Layout(num_materials=4, suns_per_material=2, resolution=TINY.resolution, shard_size=4)
    store = create_store(
        str(tmp_path / "r.zarr"),
        layout,
        {"render": TINY.to_dict(), "geometry_hash": worker.info["geometry_hash"]},
    )
    results = []
    for i, spec in enumerate(specs):
        suns = sample_suns(np.random.default_rng(derive_seed(0, i)), 2)
        results.append(
            worker.render_material(load_maps(spec), suns, [derive_seed(0, i, k) for k in range(2)])
        )
    for shard in range(layout.num_shards):
        mats = layout.shard_materials(shard)
        records = [
            {"kind": specs[i].kind, "source_id": specs[i].source_id, "spec": specs[i].to_dict()}
            for i in mats
        ]
        write_shard(
            store, shard, payload_from_renders(layout, shard, [results[i] for i in mats], records)
        )
    for i in range(layout.num_samples):
        x = store.sample(i)
        res = results[layout.material_of_sample(i)]
        truth = res.renders[i % 2]
        np.testing.assert_allclose(x.render, truth.radiance, rtol=2e-3, atol=1e-4)  # float16
        for name, arr in res.maps.as_dict().items():
            tol = 0.012 if name in ("diffuse", "specular") else 0.5 / 255 + 1e-6
            np.testing.assert_allclose(x.maps[name], arr, atol=tol, err_msg=name)
        assert x.seed == truth.seed and x.sun.turbidity == pytest.approx(truth.sun.turbidity)
        assert x.kind == specs[layout.material_of_sample(i)].kind
