"""The quality comparison (``benchmarks.quality``): baselines must pair with the ground
truth sample by sample, and (slow) the whole command end to end at the tiny scale."""

from __future__ import annotations

import os
import re
import subprocess
import sys

import numpy as np
import pytest
from PIL import Image

from benchmarks.quality import SCALES, load_json, save_json
from benchmarks.quality_report import QualityError, check_pairs, findings
from storage.reader import Store
from storage.schema import Layout
from storage.writer import create_store, write_shard
from tests.storage_helpers import synthetic_payload

LAYOUT = Layout(num_materials=4, suns_per_material=2, resolution=16, shard_size=4)


def store(path, seed: int, shards=(0, 1)) -> Store:
    s = create_store(str(path), LAYOUT, {"samples": 4})
    for shard in shards:
        write_shard(s, shard, synthetic_payload(LAYOUT, shard, seed=seed))
    return s


def test_a_baseline_must_pair_with_the_truth_sample_by_sample(tmp_path):
    truth = store(tmp_path / "truth.zarr", seed=0)
    check_pairs(truth, store(tmp_path / "same.zarr", seed=0))
    with pytest.raises(QualityError, match="sun_direction differs"):
        check_pairs(truth, store(tmp_path / "other.zarr", seed=1))
    with pytest.raises(QualityError, match="not every shard is committed"):
        check_pairs(truth, store(tmp_path / "half.zarr", seed=0, shards=(0,)))


def _row(psnr, flip, ms, parameters=None):
    return {"overall": {"psnr": psnr, "ssim": 0.9, "flip": flip}, "ms": ms,
            "parameters": parameters}  # fmt: skip


def test_the_findings_name_the_cheapest_cycles_setting_that_matches_the_network():
    rows = {
        "unet": _row(30.0, 0.10, 50.0),
        "test-1spp": _row(20.0, 0.30, 70.0),
        "test-1spp-oidn": _row(29.0, 0.09, 400.0),
        "test-4spp": _row(25.0, 0.20, 200.0),
        "test-4spp-oidn": _row(31.0, 0.05, 600.0),
        "zf-fixed": _row(27.0, 0.2, 1.0, 40e6),
        "unet-fixed": _row(33.0, 0.1, 1.0, 4e6),
        "reference": _row(38.0, 0.02, 0.0),
    }
    text = "\n".join(findings(rows, (1, 4), 2048))
    assert "(Cycles 1 spp) takes 70.0 ms, 1.4x ours" in text
    assert "PSNR: ours scores 30; the cheapest Cycles setting at least as good is " \
        "Cycles 4 spp + OIDN (31) at 600.0 ms a frame, 12.0x ours" in text  # fmt: skip
    assert "FLIP: ours scores 0.1; the cheapest Cycles setting at least as good is " \
        "Cycles 1 spp + OIDN (0.09) at 400.0 ms" in text  # fmt: skip
    assert "33.00 dB against Zsolnai-Fehér's 27.00 dB, with 4.0 M parameters against 40.0 M" in text
    assert "8.00 dB under" in text
    rows["test-4spp-oidn"] = _row(29.5, 0.05, 600.0)
    assert "PSNR: no Cycles setting measured reaches ours (30); the best, Cycles 4 spp + OIDN, " \
        "scores 29.5" in "\n".join(findings(rows, (1, 4), 2048))  # fmt: skip


@pytest.mark.slow
def test_a_work_record_write_that_fails_leaves_the_old_record_and_no_part(tmp_path):
    path = tmp_path / "timings.json"
    assert load_json(path) == {}
    save_json(path, {"cycles-1spp": 60.7})
    with pytest.raises(TypeError):
        save_json(path, {"cycles-2spp": object()})  # fails while the new file is written
    assert load_json(path) == {"cycles-1spp": 60.7}
    assert [p.name for p in tmp_path.iterdir()] == ["timings.json"]


def test_the_quality_command_end_to_end_at_the_tiny_scale(tmp_path):
    """Every step on real stores, runs and renders: the report has a row for each method
    with finite numbers, the picture grid has every row; a second run trains nothing."""
    from ray.cluster_utils import Cluster

    work, doc = tmp_path / "work", tmp_path / "doc" / "quality.md"
    head = {"num_cpus": 2, "node_ip_address": "127.0.0.1"}
    cluster = Cluster(initialize_head=True, head_node_args=head)
    try:
        env = {**os.environ, "RAY_ADDRESS": cluster.address, "RAY_AUTH_MODE": "disabled"}
        cmd = [sys.executable, "-m", "benchmarks.quality", "--scale", "tiny", "--work", str(work),
               "--doc", str(doc)]  # fmt: skip
        r = subprocess.run(cmd, capture_output=True, text=True, env=env, timeout=1500)
        assert r.returncode == 0, (r.stdout[-3000:], r.stderr[-3000:])
        again = subprocess.run([*cmd, "--steps", "train,report"], capture_output=True, text=True,
                               env=env, timeout=600)  # fmt: skip
        assert again.returncode == 0, again.stderr[-3000:]
        assert "trainer train" not in again.stdout  # every run had reached its last epoch
    finally:
        cluster.shutdown()
    text = doc.read_text()
    scale = SCALES["tiny"]
    labels = ["ours (U-Net, L1)", "ours without skips (L1)", "Zsolnai-Fehér",
              "ours, trained on the same fixed-sun data", "Cycles 2 spp + OIDN",
              f"ground truth vs {scale.reference_spp} spp, all"]  # fmt: skip
    labels += [f"Cycles {spp} spp" for spp in scale.baselines]
    for label in labels:
        row = next((line for line in text.splitlines() if line.startswith(f"| {label}")), None)
        assert row is not None, label
        numbers = [float(v) for v in re.findall(r"\| (-?\d+\.\d+)", row)]
        assert numbers and all(np.isfinite(numbers)), row
    assert "VGG16" in text and "held-out materials only" in text
    grid = Image.open(doc.parent / "img" / "quality-grid.png")
    rows = scale.fixed[1] + scale.test[1]  # fixed-sun uniform rows, then procedural ones
    assert grid.size == (5 * 256, 26 + rows * 256)


def test_frame_times_rows_every_method_from_one_run_and_refuses_bad_settings():
    """``benchmarks.frame_times`` on real networks and a real Blender (32², tiny spp): a row
    for each network and each Cycles setting, positive times, ours the unit."""
    cmd = [sys.executable, "-m", "benchmarks.frame_times", "--resolution", "32", "--spp", "1",
           "--truth", "2", "--frames", "1", "--iters", "2"]  # fmt: skip
    r = subprocess.run(cmd, capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stderr[-3000:]
    rows = dict(re.findall(r"^\| ([^|]+?) \| (\d+\.\d) \| \d+\.\d\d \|$", r.stdout, re.M))
    assert list(rows) == ["ours (U-Net)", "ours without skips", "Zsolnai-Fehér", "Cycles 1 spp",
                          "Cycles 1 spp + OIDN", "Cycles 2 spp (the ground truth)"]  # fmt: skip
    assert all(float(ms) > 0 for ms in rows.values())
    assert "| ours (U-Net) | " in r.stdout and " | 1.00 |" in r.stdout
    for bad, says in ((["--spp", "1,x"], "--spp '1,x' is not"), (["--resolution", "40"], "16")):
        r = subprocess.run([*cmd[:3], *bad], capture_output=True, text=True, timeout=60)
        assert r.returncode == 2 and says in r.stderr.strip().splitlines()[-1], r.stderr
