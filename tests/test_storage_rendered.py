"""A store of real Blender renders: what the farm will write, read back faithfully."""

from __future__ import annotations

import numpy as np
import pytest

from render_jobs.materials import specs_from_sources
from tests.storage_helpers import rendered_store

pytestmark = pytest.mark.slow


def test_rendered_store_round_trip(worker, tmp_path):
    sources = ["uniform:2", "procedural:2"]
    specs = specs_from_sources(sources, dataset_seed=0)
    store, results = rendered_store(worker, str(tmp_path / "r.zarr"), sources, 2, 4)
    layout = store.layout
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
