"""The store on S3: a real S3-compatible server (moto in server mode) on 127.0.0.1."""

from __future__ import annotations

import os
import socket
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from storage.dataset import Dataset
from storage.reader import ShardStore
from storage.writer import create_store, write_shard
from tests.storage_helpers import synthetic_payload
from tests.test_storage import LAYOUT, shards

BIN = Path(sys.executable).parent


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@pytest.fixture(scope="module")
def s3():
    port = free_port()
    proc = subprocess.Popen(
        [str(BIN / "moto_server"), "-H", "127.0.0.1", "-p", str(port)],
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
    )
    endpoint = f"http://127.0.0.1:{port}"
    deadline = time.time() + 30
    while time.time() < deadline:
        try:
            socket.create_connection(("127.0.0.1", port), timeout=0.5).close()
            break
        except OSError:
            time.sleep(0.2)
    else:
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


def test_write_read_and_verify_on_s3(s3):
    endpoint, opts = s3
    url = "s3://shaderball/set.zarr"
    store = create_store(url, LAYOUT, {"samples": 8}, storage_options=opts)
    for shard in (0, 2, 3):
        write_shard(store, shard, synthetic_payload(LAYOUT, shard))
    reader = ShardStore(url, opts)
    assert reader.committed_shards() == [0, 2, 3]
    assert reader.shard_state(1) == "empty"
    np.testing.assert_array_equal(
        reader.sample(13).render, synthetic_payload(LAYOUT, 2).renders[1].astype(np.float32)
    )
    assert len(Dataset([reader])) == 6 + 6 + 3
    write_shard(store, 1, synthetic_payload(LAYOUT, 1))  # a commit from another writer shows
    assert reader.committed_shards() == [0, 1, 2, 3]
    env = {
        **os.environ,
        "AWS_ACCESS_KEY_ID": "test",
        "AWS_SECRET_ACCESS_KEY": "test",
        "AWS_ENDPOINT_URL": endpoint,
        "AWS_DEFAULT_REGION": "us-east-1",
    }
    r = shards("verify", url, env=env)
    assert r.returncode == 0, r.stdout + r.stderr
    assert "OK: 4 committed shard(s) checked" in r.stdout
    r = shards("ls", url, env=env)
    assert r.stdout.count("committed") == 4
