"""Baselines as real features: Cycles at few samples with OpenImageDenoise, in stores whose
samples pair with the ground truth's (same materials, suns and Cycles seeds)."""

from __future__ import annotations

import numpy as np
import pytest

from render_jobs.materials.procedural import procedural_maps
from render_jobs.process import RenderProcess
from render_jobs.specs import RenderSettings
from render_jobs.sun import sun_from_angles
from storage.reader import Store
from tests.test_farm import farm

pytestmark = pytest.mark.slow


def radiance(settings: RenderSettings, maps, sun, seed: int = 7) -> np.ndarray:
    with RenderProcess(settings) as p:
        return p.render_material(maps, [sun], [seed], timeout=300).renders[0].radiance


def test_oidn_lowers_the_error_of_a_one_sample_render():
    maps, sun = procedural_maps(3, 64), sun_from_angles(40, 30, 3)
    reference = radiance(RenderSettings(resolution=64, samples=128, threads=2), maps, sun)
    raw = radiance(RenderSettings(resolution=64, samples=1, threads=2), maps, sun)
    oidn = radiance(RenderSettings(resolution=64, samples=1, threads=2, denoise=True), maps, sun)
    raw_err, oidn_err = np.abs(raw - reference).mean(), np.abs(oidn - reference).mean()
    assert np.abs(oidn - raw).mean() > 0.2 * raw_err  # it changed the render
    assert oidn_err < 0.5 * raw_err, (raw_err, oidn_err)  # and brought it nearer the truth


def test_a_baseline_store_pairs_with_its_ground_truth_sample_by_sample(tmp_path):
    common = ["-m", "uniform:2", "-m", "procedural:1", "--suns", "2", "--shard-size", "2",
              "--resolution", "32", "--workers", "1", "--no-ray-dashboard"]  # fmt: skip
    truth, base = tmp_path / "truth.zarr", tmp_path / "base.zarr"
    r = farm("submit", *common, "--samples", "8", "-o", truth)
    assert r.returncode == 0, r.stderr[-2000:]
    r = farm("submit", *common, "--samples", "1", "--denoise", "-o", base)
    assert r.returncode == 0, r.stderr[-2000:]
    a, b = Store(str(truth)), Store(str(base))
    for name in ("material_index", "sun_direction", "turbidity", "seed"):
        np.testing.assert_array_equal(a.group[name][:], b.group[name][:], err_msg=name)
    # (each store's maps are its own: Cycles anti-aliases the AOVs at the store's samples)
    assert a.settings["denoising"] is False and b.settings["denoising"] is True
    assert (a.settings["samples"], b.settings["samples"]) == (8, 1)
    assert not np.array_equal(a.group["renders"][:], b.group["renders"][:])
    # a resubmit must say the same: a ground-truth command cannot resume a baseline store
    r = farm("submit", *common, "--samples", "1", "-o", base)
    assert r.returncode == 1 and "settings.denoising=True" in r.stderr


def test_a_fixed_sun_dataset_renders_every_material_under_one_light(tmp_path):
    out = tmp_path / "fixed.zarr"
    args = ["submit", "-m", "uniform:3", "--suns", "1", "--shard-size", "2", "--resolution", "32",
            "--samples", "2", "--workers", "1", "--no-ray-dashboard"]  # fmt: skip
    r = farm(*args, "--fixed-sun", "0,3,4", "--fixed-turbidity", "5", "-o", out)
    assert r.returncode == 0, r.stderr[-2000:]
    store = Store(str(out))
    np.testing.assert_allclose(store.group["sun_direction"][:], [[0, 0.6, 0.8]] * 3, atol=1e-6)
    np.testing.assert_array_equal(store.group["turbidity"][:], [5.0] * 3)
    assert store.settings["fixed_sun"] == [0.0, 3.0, 4.0, 5.0]
    bad = farm(*args[:3], "--suns", "2", "--fixed-sun", "0,0,1", "-o", tmp_path / "no.zarr")
    assert bad.returncode == 1 and "--suns 1" in bad.stderr.strip().splitlines()[-1]
    below = farm(*args, "--fixed-sun", "1,0,-1", "-o", tmp_path / "no.zarr")
    assert below.returncode == 1 and "above the horizon" in below.stderr
    assert not (tmp_path / "no.zarr").exists()
