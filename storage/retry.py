"""Retrying transient object-store errors, one policy for every read and write of a store.

botocore and s3fs retry a failed request a few times within a second or two. A throttled
bucket (503 ``SlowDown``), a flapping connection or a stalled server can outlast that, and
then the error reaches the farm driver (a month-long job) or a DataLoader worker (which ends a
training run). :func:`retrying` wraps an operation so that such errors are retried with
exponential backoff and jitter (tenacity), up to ``ATTEMPTS`` tries and ``MAX_S`` seconds in
all, each retry logged once; anything else (403, 404, no such bucket, bad credentials, a
corrupt chunk) is raised at once.

Every wrapped operation is idempotent: reads, whole-object puts, and a shard's array writes,
which only ever rewrite the same bytes of a shard that is not yet committed.
"""

from __future__ import annotations

import errno
import logging
import socket

from tenacity import (
    RetryCallState,
    retry,
    retry_if_exception,
    stop_after_attempt,
    stop_after_delay,
    wait_random_exponential,
)

log = logging.getLogger("shaderball.storage")

ATTEMPTS = 8
MAX_S = 120.0
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


def transient(exc: BaseException) -> bool:
    """Whether ``exc`` (or an error it was raised from) is worth retrying."""
    seen = 0
    while exc is not None and seen < 8:
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


def _log_retry(state: RetryCallState) -> None:
    exc = state.outcome.exception() if state.outcome else None
    name = getattr(state.fn, "__qualname__", "object-store call")
    log.warning(
        "%s: %s: %s; retry %d in %.1f s",
        name,
        type(exc).__name__,
        str(exc).splitlines()[0] if str(exc) else "",
        state.attempt_number,
        state.next_action.sleep if state.next_action else 0.0,
    )


def retrying(fn=None, *, attempts: int = ATTEMPTS, max_s: float = MAX_S, base_s: float = 0.5):
    """Decorate ``fn`` with the policy (see the module docstring)."""
    policy = retry(
        retry=retry_if_exception(transient),
        wait=wait_random_exponential(multiplier=base_s, max=20.0),
        stop=stop_after_attempt(attempts) | stop_after_delay(max_s),
        before_sleep=_log_retry,
        reraise=True,
    )
    return policy if fn is None else policy(fn)
