"""Shared fixtures: one real Blender worker process for the session (64 px, 8 spp)."""

from __future__ import annotations

import numpy as np
import pytest

from render_jobs.materials.uniform import uniform_maps
from render_jobs.specs import RenderSettings, UniformValues
from render_jobs.worker import RenderProcess

TINY = RenderSettings(resolution=64, samples=8, threads=2)


@pytest.fixture(scope="session")
def worker():
    """A kept-loaded shaderball renderer in a Blender worker process."""
    with RenderProcess(TINY) as w:
        yield w


def grey_uniform(**overrides) -> UniformValues:
    values = {
        "diffuse": (0.6, 0.6, 0.6),
        "specular": (0.1, 0.1, 0.1),
        "roughness": 0.5,
        "normal_tilt_deg": 0.0,
        "normal_azimuth_deg": 0.0,
    }
    values.update(overrides)
    return UniformValues(**values)


@pytest.fixture
def grey_maps():
    return uniform_maps(grey_uniform(), "grey")


def inside(mask: np.ndarray, threshold: float = 0.99) -> np.ndarray:
    """Pixels fully covered by the material: ``(H, W) bool``."""
    return mask[0] > threshold


@pytest.fixture(scope="session")
def tiny_store(worker, tmp_path_factory):
    """A real rendered store for the trainer: 4 uniform + 4 procedural materials x 3 suns at
    64² (24 samples, shards of 2 materials)."""
    from tests.storage_helpers import rendered_store

    path = tmp_path_factory.mktemp("trainer") / "tiny.zarr"
    store, _ = rendered_store(worker, str(path), ["uniform:4", "procedural:4"], 3, 6)
    return store
