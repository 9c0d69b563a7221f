"""Retrying transient object-store errors, one policy for every read and write of a store.

botocore and s3fs retry a failed request a few times within a second or two. A throttled
bucket (503 ``SlowDown``), a flapping connection or a stalled server can outlast that, and
then the error reaches the farm driver (a month-long job) or a DataLoader worker (which ends a
training run). :func:`retrying` wraps an operation so that such errors are retried with
exponential backoff and jitter (tenacity), each retry logged once, for :func:`max_seconds`
at most (``SHADERBALL_STORE_RETRY_S``, 120 by default) and ``ATTEMPTS`` tries, or one try per
``MAX_WAIT_S`` (the longest wait) where that allows more; anything else (403, 404, no
such bucket, bad credentials, a corrupt chunk) is raised at once. A transient error that
outlasts the tries is raised as :class:`StoreUnreachable`, an ``OSError`` with a one-line
message (what failed, how, how long it was tried), from the last error; it is not transient
itself, so an operation that calls another gives up when the inner one does.

Every wrapped operation is idempotent: reads, whole-object puts, and a shard's array writes,
which only ever rewrite the same bytes of a shard that is not yet committed.
"""

from __future__ import annotations

import errno
import functools
import logging
import math
import os
import socket

from tenacity import (
    RetryCallState,
    retry,
    retry_if_exception,
    stop_after_attempt,
    stop_before_delay,
    wait_random_exponential,
)

from storage.errors import SettingError

log = logging.getLogger("shaderball.storage")

ATTEMPTS = 8
MAX_WAIT_S = 20.0
#: the environment variable that sets :func:`max_seconds` (read when an operation is first
#: tried, so that a bad value is a command's one-line error, not a failed import)
MAX_S_ENV = "SHADERBALL_STORE_RETRY_S"


def _max_s(value: str | None) -> float:
    """Seconds an operation is tried at most: ``value`` (from :data:`MAX_S_ENV`), or 120."""
    if value is None or value == "":
        return 120.0
    try:
        seconds = float(value)
    except ValueError:
        seconds = -1.0
    if not seconds > 0:
        raise SettingError(f"{MAX_S_ENV}={value!r}: expected a number of seconds above 0")
    return seconds


@functools.cache
def max_seconds() -> float:
    """Seconds an operation is tried at most, from :data:`MAX_S_ENV` (read once)."""
    return _max_s(os.environ.get(MAX_S_ENV))


#: HTTP statuses worth another try: throttling, timeouts, server-side failures
TRANSIENT_STATUS = {408, 429, 500, 502, 503, 504}
TRANSIENT_CODES = {
    "SlowDown",
    "Throttling",
    "ThrottlingException",
    "RequestTimeout",
    "RequestTimeTooSkewed",
    "InternalError",
    "ServiceUnavailable",
}
#: errno values s3fs gives throttling and unavailability (its translation of S3 error codes)
TRANSIENT_ERRNOS = {errno.EBUSY, errno.EAGAIN, errno.ETIMEDOUT, errno.ECONNRESET}
#: names of transport errors of botocore / aiohttp (matched by name: neither is imported here)
TRANSIENT_NAMES = {
    "EndpointConnectionError",
    "ConnectionClosedError",
    "ReadTimeoutError",
    "ConnectTimeoutError",
    "ResponseStreamingError",
    "ServerDisconnectedError",
    "ClientOSError",
    "ClientPayloadError",
    "IncompleteRead",
    "FSTimeoutError",
}


class StoreUnreachable(OSError):
    """A transient object-store error that lasted through every try."""


def transient(exc: BaseException) -> bool:
    """Whether ``exc`` (or an error it was raised from) is worth retrying."""
    seen = 0
    while exc is not None and seen < 8:
        if isinstance(exc, StoreUnreachable):
            return False
        if isinstance(exc, FileNotFoundError | PermissionError | IsADirectoryError):
            return False
        if isinstance(exc, ConnectionError | TimeoutError | socket.timeout):
            return True
        if type(exc).__name__ in TRANSIENT_NAMES:
            return True
        response = getattr(exc, "response", None)
        if isinstance(response, dict):
            err = response.get("Error", {})
            status = response.get("ResponseMetadata", {}).get("HTTPStatusCode")
            if err.get("Code") in TRANSIENT_CODES or status in TRANSIENT_STATUS:
                return True
        if isinstance(exc, OSError) and (
            exc.errno in TRANSIENT_ERRNOS or any(c in str(exc) for c in TRANSIENT_CODES)
        ):
            return True  # s3fs re-raises S3 errors as OSError: 503 SlowDown as EBUSY
        exc, seen = exc.__cause__ or exc.__context__, seen + 1
    return False


def _failure(state: RetryCallState) -> str:
    """``operation: ErrorType: the error's first line`` of the try that just failed."""
    exc = state.outcome.exception() if state.outcome else None
    name = getattr(state.fn, "__qualname__", "object-store call")
    first = str(exc).splitlines()[0] if str(exc) else ""
    return f"{name}: {type(exc).__name__}: {first}"


def _log_retry(state: RetryCallState) -> None:
    sleep = state.next_action.sleep if state.next_action else 0.0
    log.warning("%s; retry %d in %.1f s", _failure(state), state.attempt_number, sleep)


def _give_up(state: RetryCallState):
    raise StoreUnreachable(
        f"{_failure(state)} (tried {state.attempt_number} times in "
        f"{state.seconds_since_start:.0f} s)"
    ) from state.outcome.exception()


def retrying(
    fn=None, *, attempts: int | None = None, max_s: float | None = None, base_s: float = 0.5
):
    """Decorate ``fn`` with the policy (see the module docstring); ``max_s`` defaults to
    :func:`max_seconds`, read at the first call."""
    if fn is None:
        return functools.partial(retrying, attempts=attempts, max_s=max_s, base_s=base_s)
    policy = []

    @functools.wraps(fn)
    def tried(*args, **kwargs):
        if not policy:
            seconds = max_seconds() if max_s is None else max_s
            tries = attempts or max(ATTEMPTS, math.ceil(seconds / MAX_WAIT_S) + 1)
            policy.append(
                retry(
                    retry=retry_if_exception(transient),
                    wait=wait_random_exponential(multiplier=base_s, max=MAX_WAIT_S),
                    stop=stop_after_attempt(tries) | stop_before_delay(seconds),
                    before_sleep=_log_retry,
                    retry_error_callback=_give_up,
                )(fn)
            )
        return policy[0](*args, **kwargs)

    return tried
