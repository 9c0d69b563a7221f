"""The store on S3: a real S3-compatible server (moto in server mode) on 127.0.0.1."""

from __future__ import annotations

import os
import sys
from pathlib import Path

import numpy as np

from storage.catalog import Catalog
from storage.reader import Store
from storage.writer import create_store, write_shard
from tests.storage_helpers import synthetic_payload
from tests.test_storage import LAYOUT, shards

BIN = Path(sys.executable).parent


def test_write_read_and_verify_on_s3(s3):
    endpoint, opts = s3
    url = "s3://shaderball/set.zarr"
    store = create_store(url, LAYOUT, {"samples": 8}, storage_options=opts)
    for shard in (0, 2, 3):
        write_shard(store, shard, synthetic_payload(LAYOUT, shard))
    reader = Store(url, opts)
    assert reader.committed_shards() == [0, 2, 3]
    assert reader.shard_state(1) == "empty"
    np.testing.assert_array_equal(
        reader.sample(13).render, synthetic_payload(LAYOUT, 2).renders[1].astype(np.float32)
    )
    cat = Catalog.snapshot([url], seed=0, holdout_fraction=0.0, storage_options=opts)
    assert len(cat.split("train", opts)) == 6 + 6 + 3
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
