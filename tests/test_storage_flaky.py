"""The store over a flaky object store: a fault-injecting proxy (503 SlowDown, connection
resets, stalls) in front of the tests' S3 server on 127.0.0.1; the retry policy alone."""

from __future__ import annotations

import errno
import logging
import time

import numpy as np
import pytest
from botocore.exceptions import ClientError

from storage.errors import SettingError
from storage.reader import Store
from storage.retry import StoreUnreachable, _max_s, retrying, transient
from storage.verify import verify
from storage.writer import create_store, write_shard
from tests.flaky_proxy import FlakyProxy
from tests.storage_helpers import synthetic_payload
from tests.test_storage import LAYOUT


def client_error(code: str, status: int) -> ClientError:
    body = {"Error": {"Code": code}, "ResponseMetadata": {"HTTPStatusCode": status}}
    return ClientError(body, "GetObject")


@pytest.mark.parametrize(
    "exc,want",
    [
        (ConnectionResetError(104, "reset"), True),
        (TimeoutError(), True),
        (client_error("SlowDown", 503), True),
        (client_error("InternalError", 500), True),
        (OSError("An error occurred (SlowDown) when calling PutObject"), True),
        (OSError(errno.EBUSY, "Service Unavailable"), True),
        (client_error("AccessDenied", 403), False),
        (client_error("NoSuchBucket", 404), False),
        (PermissionError("Access Denied"), False),
        (FileNotFoundError("nope"), False),
        (ValueError("checksum"), False),
    ],
)
def test_which_errors_are_transient(exc, want):
    assert transient(exc) is want
    try:  # the cause counts too, as s3fs re-raises
        raise RuntimeError("wrapped") from exc
    except RuntimeError as wrapped:
        assert transient(wrapped) is want


def test_transient_errors_are_retried_and_logged_permanent_ones_raised_at_once(caplog):
    calls = []

    @retrying(base_s=0.01)
    def flaky():
        calls.append(1)
        if len(calls) < 3:
            raise ConnectionResetError(104, "Connection reset by peer")
        return "ok"

    with caplog.at_level(logging.WARNING, "shaderball.storage"):
        assert flaky() == "ok"
    assert len(calls) == 3 and len(caplog.records) == 2
    assert "ConnectionResetError" in caplog.records[0].getMessage()

    @retrying(base_s=0.01, attempts=4)
    def denied():
        calls.append(1)
        raise PermissionError("Access Denied")

    calls.clear()
    with pytest.raises(PermissionError):
        denied()
    assert len(calls) == 1

    @retrying(base_s=0.01, attempts=4)
    def down():
        calls.append(1)
        raise client_error("SlowDown", 503)

    @retrying(base_s=0.01)
    def calls_down():
        return down()

    calls.clear()
    with pytest.raises(StoreUnreachable) as err:
        calls_down()
    assert len(calls) == 4  # bounded, and the outer operation gives up with the inner one
    assert isinstance(err.value, OSError) and isinstance(err.value.__cause__, ClientError)
    assert str(err.value).startswith("test_transient_errors_are_retried_and_logged_perma")
    assert "down: ClientError: An error occurred (SlowDown)" in str(err.value)
    assert "(tried 4 times in 0 s)" in str(err.value) and "\n" not in str(err.value)


def test_the_retry_time_comes_from_the_environment_and_sets_the_tries():
    assert _max_s(None) == _max_s("") == 120.0 and _max_s("2.5") == 2.5
    for bad in ("0", "-1", "soon", "nan"):
        with pytest.raises(SettingError, match=f"SHADERBALL_STORE_RETRY_S={bad!r}: expected"):
            _max_s(bad)
    calls = []

    @retrying(base_s=0.0, max_s=600.0)
    def down():
        calls.append(1)
        raise ConnectionResetError(104, "reset")

    with pytest.raises(StoreUnreachable, match="tried 31 times"):
        down()  # 600 s allow 31 tries of at most 20 s apart (8 for the default 120 s)
    assert len(calls) == 31


def flaky_options(opts: dict, endpoint: str) -> dict:
    """Through the proxy, with short timeouts and botocore's own retries cut to one
    attempt (s3fs still makes its own few)."""
    client = {**opts["client_kwargs"], "endpoint_url": endpoint}
    retries = {"mode": "standard", "total_max_attempts": 1}  # one try, the first included
    config = {"read_timeout": 1.0, "connect_timeout": 1.0, "retries": retries}
    return {**opts, "client_kwargs": client, "config_kwargs": config}


def test_a_store_written_and_read_through_faults_is_whole(s3):
    upstream, opts = s3
    url = "s3://shaderball/flaky.zarr"
    with FlakyProxy(upstream, every=30, stall_s=1.5, burst=2) as proxy:
        o = flaky_options(opts, proxy.endpoint)
        store = create_store(url, LAYOUT, {"samples": 8}, storage_options=o)
        for shard in range(LAYOUT.num_shards):
            write_shard(store, shard, synthetic_payload(LAYOUT, shard))
        reader = Store(url, o)
        got = [reader.sample(i).render for i in range(LAYOUT.num_samples)]
        assert verify(Store(url, o)).ok
    assert all(proxy.faults[k] for k in ("503", "reset", "stall")), proxy.faults
    clean = Store(url, opts)  # straight to the server: the same bytes
    assert clean.committed_shards() == list(range(LAYOUT.num_shards))
    for i, render in enumerate(got):
        np.testing.assert_array_equal(render, clean.sample(i).render)


def test_a_permanent_error_fails_at_once(s3):
    upstream, opts = s3
    with FlakyProxy(upstream, every=10**9, deny="/denied.zarr") as proxy:
        o = flaky_options(opts, proxy.endpoint)
        t0 = time.perf_counter()
        with pytest.raises(PermissionError):
            create_store("s3://shaderball/denied.zarr", LAYOUT, {}, storage_options=o)
        assert time.perf_counter() - t0 < 5
    assert proxy.faults["denied"] <= 2
