"""Install extras per role: ``shaderball[train]`` alone, in a fresh virtual environment
(no Blender, no Ray), trains on a store written by the storage API; the parts it lacks say in
one line which extra to install.

The environment is filled by uv, the Makefile's installer (its cache is warm after ``make``):
what is tested is the extra's set of requirements, which pip and uv resolve alike."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

from storage.schema import Layout
from storage.writer import create_store, write_shard
from tests.storage_helpers import synthetic_payload

pytestmark = pytest.mark.slow
ROOT = Path(__file__).resolve().parent.parent


def torch_requirement() -> str:
    """The Makefile's torch: the CPU build of 2.13.0 where pip's find-links folder holds it
    (a plain ``torch==2.13.0`` resolves to PyPI's CUDA build and its gigabytes of downloads)."""
    cpu = list(Path("/opt/wheels").glob("torch-2.13.0+cpu-*.whl"))
    return "torch==2.13.0+cpu" if cpu else "torch==2.13.0"


def test_the_train_extra_alone_trains_and_names_the_missing_extras(tmp_path):
    layout = Layout(num_materials=8, suns_per_material=2, resolution=32, shard_size=4)
    store = create_store(str(tmp_path / "tiny.zarr"), layout, {"samples": 4})
    for shard in range(layout.num_shards):
        write_shard(store, shard, synthetic_payload(layout, shard))
    venv = tmp_path / "venv"
    subprocess.run([sys.executable, "-m", "venv", "--without-pip", str(venv)], check=True)
    uv = str(Path(sys.executable).parent / "uv")
    links = ["--find-links", "/opt/wheels"] if Path("/opt/wheels").is_dir() else []
    install = subprocess.run(
        [uv, "pip", "install", "--quiet", "--python", str(venv / "bin" / "python"), *links,
         f"{ROOT}[train]", torch_requirement()],
        capture_output=True, text=True, timeout=900, env={**os.environ, "UV_HTTP_RETRIES": "10"},
    )  # fmt: skip
    assert install.returncode == 0, install.stderr[-3000:]
    py = str(venv / "bin" / "python")
    for module in ("bpy", "ray"):  # (aiohttp comes with s3fs, jinja2 with torch)
        r = subprocess.run([py, "-c", f"import {module}"], capture_output=True)
        assert r.returncode != 0, f"{module} came with [train]"
    run = tmp_path / "run"
    r = subprocess.run(
        [str(venv / "bin" / "trainer"), "launch", "--store", str(tmp_path / "tiny.zarr"),
         "--out", str(run), "--epochs", "1", "--recipe", "paper", "--loss", "l1",
         "--batch-size", "2",
         "--workers", "0", "--width", "16"],
        capture_output=True, text=True, timeout=600, cwd=tmp_path,
    )  # fmt: skip
    assert r.returncode == 0, r.stderr[-3000:]
    assert list((run / "checkpoints").glob("*.pt"))
    farm = [str(venv / "bin" / "farm"), "submit", "-m", "uniform:1", "-o", str(tmp_path / "x.zarr")]
    r = subprocess.run(farm, capture_output=True, text=True, cwd=tmp_path)
    assert r.returncode == 1
    assert r.stderr.strip() == (
        "Error: farm submit needs ray, which this install lacks: pip install 'shaderball[farm]'"
    )
    assert not (tmp_path / "x.zarr").exists()
    export = [str(venv / "bin" / "trainer"), "export", "--checkpoint", str(run), "-o", "b.onnx"]
    r = subprocess.run(export, capture_output=True, text=True, cwd=tmp_path)
    assert r.returncode == 1
    assert r.stderr.strip() == (
        "Error: trainer export needs onnx, which this install lacks: "
        "pip install 'shaderball[export]'"
    )
    assert not (tmp_path / "b.onnx").exists()
