"""Shared fixtures: a real Blender worker (64 px, 8 spp), a tiny rendered store, an S3 server."""

from __future__ import annotations

import contextlib
import os
import socket
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import pytest

from render_jobs.materials.uniform import uniform_maps
from render_jobs.process import RenderProcess
from render_jobs.specs import RenderSettings, UniformValues

TINY = RenderSettings(resolution=64, samples=8, threads=2)
# the benchmarks the tests run write their tables here, not into benchmarks/results
os.environ.setdefault("SHADERBALL_BENCH_RESULTS", tempfile.mkdtemp(prefix="bench-results-"))
BIN = Path(sys.executable).parent


def pytest_configure(config) -> None:
    """Once, before any test worker starts: the Ray token that token-authenticated Ray
    clusters share (``~/.ray/auth_token``), so that two tests starting the first such
    clusters of a fresh machine at once do not each write a different one."""
    if not hasattr(config, "workerinput") and not (Path.home() / ".ray" / "auth_token").exists():
        subprocess.run([str(BIN / "ray"), "get-auth-token", "--generate"], capture_output=True)


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


def s3_env(endpoint: str, **extra: str) -> dict[str, str]:
    """The environment that points botocore / s3fs at the test S3 server ``endpoint``."""
    return {
        "AWS_ACCESS_KEY_ID": "test",
        "AWS_SECRET_ACCESS_KEY": "test",
        "AWS_DEFAULT_REGION": "us-east-1",
        "AWS_ENDPOINT_URL": endpoint,
        **extra,
    }


def wait_for_port(port: int, proc: subprocess.Popen, timeout: float) -> bool:
    """Whether 127.0.0.1:``port`` answers within ``timeout`` seconds while ``proc`` runs."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline and proc.poll() is None:
        with contextlib.suppress(OSError):
            socket.create_connection(("127.0.0.1", port), timeout=0.5).close()
            return True
        time.sleep(0.2)
    return False


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@pytest.fixture(scope="session")
def s3():
    """A real S3-compatible server (moto) on 127.0.0.1 with bucket ``shaderball``:
    ``(endpoint, storage_options)``."""
    port = free_port()
    proc = subprocess.Popen(
        [str(BIN / "moto_server"), "-H", "127.0.0.1", "-p", str(port)],
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
    )
    endpoint = f"http://127.0.0.1:{port}"
    if not wait_for_port(port, proc, 30):
        proc.kill()
        pytest.fail("moto_server did not start")
    import boto3

    boto3.client(
        "s3",
        endpoint_url=endpoint,
        aws_access_key_id="test",
        aws_secret_access_key="test",
        region_name="us-east-1",
    ).create_bucket(Bucket="shaderball")
    opts = {
        "key": "test",
        "secret": "test",
        "client_kwargs": {"endpoint_url": endpoint, "region_name": "us-east-1"},
    }
    yield endpoint, opts
    proc.terminate()
    proc.wait(10)
