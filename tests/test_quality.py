"""The quality comparison (``benchmarks.quality``): baselines must pair with the ground
truth sample by sample, the viewer's picture shows the median sample, and (slow) the whole
command end to end at the tiny scale."""

from __future__ import annotations

import json
import os
import re
import subprocess
import sys

import numpy as np
import pytest
from PIL import Image

from benchmarks.quality_plan import SCALES, load_json, save_json
from benchmarks.quality_report import (
    QualityError,
    check_pairs,
    difference_table,
    findings,
    per_sample,
    read_sample_table,
)
from benchmarks.viewer_picture import Pick, median_sample
from storage.reader import Store
from storage.schema import Layout
from storage.writer import create_store, write_shard
from tests.ray_local import local_cluster
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


def _scored(psnr, flip, ms, parameters=None):
    """A report row with per-sample scores: 2 suns a material."""
    n = len(psnr)
    ps = per_sample(range(n), [i // 2 for i in range(n)], np.c_[psnr, np.full(n, 0.9), flip])
    overall = {"psnr": float(np.mean(psnr)), "ssim": 0.9, "flip": float(np.mean(flip))}
    return {"overall": overall, "ms": ms, "parameters": parameters, "per_sample": ps}


def test_each_comparison_of_the_findings_has_its_paired_difference_and_interval():
    """20 samples of 10 materials: a setting better by exactly 1 dB everywhere is resolved; one
    0.5 dB below ours on average, but 4 dB above or below it material by material, is not."""
    base = np.random.default_rng(0).normal(30, 2, 20)
    swing = np.repeat([-4.0, 4.0] * 5, 2)  # whole materials, mean 0
    flip = np.full(20, 0.10)
    rows = {
        "unet": _scored(base, flip, 50.0),
        "test-1spp": _scored(base - 10, flip + 0.2, 70.0),
        "test-1spp-oidn": _scored(base - 0.5 + swing, flip - 0.01, 400.0),
        "test-4spp": _scored(base - 5, flip + 0.1, 200.0),
        "test-4spp-oidn": _scored(base + 1, flip - 0.05, 600.0),
        "zf-fixed": _scored(base - 3, flip, 1.0, 40e6),
        "unet-fixed": _scored(base, flip, 1.0, 4e6),
        "reference": _row(38.0, 0.02, 0.0),
    }
    text = "\n".join(findings(rows, (1, 4), 2048))
    mean = base.mean()
    assert f"good is Cycles 4 spp + OIDN ({mean + 1:.4g}) at 600.0 ms a frame, 12.0x ours; " \
        "ours less it: -1.00 [-1.00, -1.00] dB (the interval excludes 0)." in text  # fmt: skip
    near = re.search(rf"The closest setting under ours is Cycles 1 spp \+ OIDN \({mean - 0.5:.4g}"
                     r"\); ours less it: \+0\.50 \[(\S+), (\S+)\] dB \(the interval holds 0: "
                     r"this test set cannot tell them apart\)\.", text)  # fmt: skip
    assert near and float(near[1]) < 0 < float(near[2]), text
    assert "FLIP: ours scores 0.1; the cheapest Cycles setting at least as good is Cycles 1 spp " \
        "+ OIDN (0.09) at 400.0 ms a frame, 8.0x ours; ours less it: +0.0100 [+0.0100, " \
        "+0.0100] (the interval excludes 0). The closest setting under ours is Cycles 4 spp " \
        "(0.2); ours less it: -0.1000" in text  # fmt: skip
    assert f"against Zsolnai-Fehér's {mean - 3:.2f} dB; ours less it: +3.00 [+3.00, +3.00] " \
        "dB (the interval excludes 0), with 4.0 M" in text  # fmt: skip
    table = difference_table(rows, "unet", "ours", [("Cycles 1 spp", "test-1spp")])
    assert table[0] == "| ours less | PSNR dB | SSIM | FLIP | ours higher PSNR on |"
    assert table[2] == "| Cycles 1 spp | +10.00 [+10.00, +10.00] | +0.0000 [+0.0000, +0.0000] " \
        "| -0.2000 [-0.2000, -0.2000] | 100% |"  # fmt: skip
    # rows of an older results.json, without per-sample scores: no table, no intervals
    assert difference_table({**rows, "test-1spp": _row(20.0, 0.3, 70.0)}, "unet", "ours",
                            [("Cycles 1 spp", "test-1spp")]) == []  # fmt: skip
    rows["zf-fixed"]["per_sample"]["sample"].reverse()
    with pytest.raises(QualityError, match="unet-fixed and zf-fixed were scored on other samples"):
        findings(rows, (1, 4), 2048)


def test_per_sample_scores_are_kept_in_sample_order_from_an_eval_table(tmp_path):
    path = tmp_path / "s.csv"
    rows = ["t.zarr,3,1,21.5,0.5,0.2", "t.zarr,0,0,30,0.9,0.1", "t.zarr,1,0,31,0.95,0.05"]
    path.write_text("store,sample,material,psnr_1,ssim_1,flip_1\n" + "\n".join(rows) + "\n")
    ps = read_sample_table(path)
    assert ps == {"sample": [0, 1, 3], "material": [0, 0, 1], "psnr": [30.0, 31.0, 21.5],
                  "ssim": [0.9, 0.95, 0.5], "flip": [0.1, 0.05, 0.2]}  # fmt: skip
    path.write_text(path.read_text() + "u.zarr,0,0,30,0.9,0.1\n")
    with pytest.raises(QualityError, match="samples of more than one store"):
        read_sample_table(path)


@pytest.mark.slow
def test_the_viewer_picture_shows_the_median_sample_of_its_kind_not_the_best():
    scores = {"sample": [0, 1, 2, 3, 4, 5, 6, 7], "material": [0, 0, 1, 1, 2, 2, 3, 3],
              "psnr": [30.0, 40.0, 20.0, 35.0, 50.0, 25.0, 33.0, 31.0]}  # fmt: skip
    kinds = {0: "procedural", 1: "uniform", 2: "procedural", 3: "procedural"}
    # procedural PSNRs sorted: 25 (5), 30 (0), 31 (7), 33 (6), 40 (1), 50 (4): the lower middle
    assert median_sample(scores, kinds, 2, "procedural") == Pick(7, 3, 1, 31.0)
    assert median_sample(scores, kinds, 2, "uniform") == Pick(2, 1, 0, 20.0)
    with pytest.raises(ValueError, match="no svbrdf material among the scored samples"):
        median_sample(scores, kinds, 2, "svbrdf")


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
    work, doc = tmp_path / "work", tmp_path / "doc" / "quality.md"
    cluster = local_cluster(2)
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
    labels = ["ours (the shaderball recipe)", "the paper's U-Net (L1)",
              "the paper's U-Net without skips (L1)", "Zsolnai-Fehér",
              "ours, trained on the same fixed-sun data", "Cycles 2 spp + OIDN",
              f"ground truth vs {scale.reference_spp} spp, all"]  # fmt: skip
    labels += [f"Cycles {spp} spp" for spp in scale.baselines]
    for label in labels:
        row = next((line for line in text.splitlines() if line.startswith(f"| {label}")), None)
        assert row is not None, label
        numbers = [float(v) for v in re.findall(r"\| (-?\d+\.\d+)", row)]
        assert numbers and all(np.isfinite(numbers)), row
    assert "VGG16" in text and "held-out materials only" in text
    assert (
        "with the settings its run recorded: `--recipe shaderball`, width 8, scene cues paint,"
        in text
    )
    assert re.search(
        r"Precision \(`--precision auto`; weights and losses fp32\): (bf16|fp32) \(unet, paper, ",
        text,
    )
    assert "U-Nets 16 channels wide at their first level (the paper: 64)" in text
    for run, width in (("unet", 8), ("paper", 16), ("unet-noskips", 16), ("unet-fixed", 8)):
        config = json.loads((work / "runs" / run / "config.json").read_text())
        assert config["width"] == width  # the tiny scale's widths, as the text says
        assert config["recipe"] == ("paper" if run in ("paper", "unet-noskips") else "shaderball")
    # 5 test materials: each mean PSNR of the main table has an interval around it, and each
    # comparison with ours its paired difference with an interval; 2 fixed-sun test
    # materials: differences without intervals
    main, fixed = text.split("## Fixed sun")
    ours = "ours (the shaderball recipe)"
    for label in [ours, *(f"Cycles {spp} spp" for spp in scale.baselines)]:
        row = next(line for line in main.splitlines() if line.startswith(f"| {label} |"))
        psnr, ci = row.split(" | ")[1:3]
        low, high = map(float, re.fullmatch(r"\[(-?\d+\.\d\d), (-?\d+\.\d\d)\]", ci).groups())
        assert low <= float(psnr) <= high, row
    assert f"| {ours} less | PSNR dB | SSIM | FLIP | ours higher PSNR on |" in main
    number, ci = r"[+-]\d+\.\d+", r"[+-]\d+\.\d+ \[[+-]\d+\.\d+, [+-]\d+\.\d+\]"
    for label in [
        "the paper's U-Net without skips \\(L1\\)",
        *(f"Cycles {spp} spp" for spp in scale.baselines),
    ]:
        assert re.search(rf"^\| {label} \| {ci} \| {ci} \| {ci} \| \d+% \|$", main, re.M), label
    assert "bootstrap that resamples whole materials" in main
    assert re.search(rf"^\| Zsolnai-Fehér [^|]*\| {number} \| {number} \| {number} \| \d+% \|$",
                     fixed, re.M), fixed  # fmt: skip
    # the viewer's picture: the median procedural sample beside its Cycles render, and the
    # page's PSNR the same as eval's
    picture = json.loads((doc.parent / "img" / "viewer.json").read_text())
    assert picture["kind"] == "procedural" and picture["page_psnr"] is not None, picture
    assert abs(picture["page_psnr"] - picture["psnr"]) < 0.1, picture
    assert Image.open(doc.parent / "img" / "viewer.png").size[0] >= 1000
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
    assert list(rows) == ["ours (the default recipe)", "the paper's U-Net",
                          "the paper's U-Net without skips", "Zsolnai-Fehér", "Cycles 1 spp",
                          "Cycles 1 spp + OIDN", "Cycles 2 spp (the ground truth)"]  # fmt: skip
    assert all(float(ms) > 0 for ms in rows.values())
    assert "| ours (the default recipe) | " in r.stdout and " | 1.00 |" in r.stdout
    for bad, says in ((["--spp", "1,x"], "--spp '1,x' is not"), (["--resolution", "40"], "16")):
        r = subprocess.run([*cmd[:3], *bad], capture_output=True, text=True, timeout=60)
        assert r.returncode == 2 and says in r.stderr.strip().splitlines()[-1], r.stderr
