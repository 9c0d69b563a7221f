"""Settings of ``benchmarks.learning`` given per row, and the time each row may train.

A per-row option (``--lr-scale``, ``--row-seconds``) takes ``VALUE`` for every row or
``ROW=VALUE`` for one; it is repeatable and the later value wins. A row not among those a
command trains is left alone, so one command's values may name rows it does not train.

The rows of a call with a wall-clock limit of its own (a device call's) share it
(``--seconds``, :func:`time_limit`): each row trains until its own cap (``--row-seconds``) or
until what is left of the call, less :data:`RESERVE` seconds for this row and each one after
it (start-up, preloading, scoring) and less the caps of the rows after it, whichever comes
first. So a row with no cap takes all the time the rows after it do not need: put it last.
A row that is left no time still trains :data:`LEAST` seconds and is scored where it stopped.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Collection

#: seconds kept for each row still to run besides its training: the trainer's start-up and
#: preloading, its last checkpoint, and the row's scoring
RESERVE = 45.0
#: the least time a row trains (the trainer needs a limit above 0)
LEAST = 1.0


class BadRowOption(ValueError):
    """A per-row option's value that names no row or is no value (its one-line error)."""


def per_row(
    option: str,
    values: list[str],
    names: list[str],
    rows: Collection[str],
    parse: Callable[[str], object],
    default=None,
) -> dict:
    """Each of the rows ``names``' value from ``option``'s ``values`` (``VALUE`` or
    ``ROW=VALUE``; ``rows``: every row there is), ``default`` where none is given. ``parse``
    turns a value's text into the value or raises ``ValueError`` with the words that follow
    the value in the error."""
    out = dict.fromkeys(names, default)
    for value in values:
        row, _, text = value.rpartition("=")
        try:
            parsed = parse(text)
        except ValueError as exc:
            raise BadRowOption(f"{option} {value}: {text!r} {exc}") from None
        if row and row not in rows:
            raise BadRowOption(f"{option} {value}: {row!r} is not a row (one of {', '.join(rows)})")
        out |= dict.fromkeys([row] if row in names else [] if row else names, parsed)
    return out


def seconds(text: str) -> float:
    """``--row-seconds``' value: a number of seconds above 0."""
    try:
        value = float(text)
    except ValueError:
        raise ValueError("is not a number of seconds") from None
    if not value > 0:  # also refuses nan
        raise ValueError("is not above 0")
    return value


def time_limit(
    cap: float | None, later: list[float | None], left: float | None, reserve: float = RESERVE
) -> float | None:
    """How long a row may train: its ``cap`` (``None``: none), or less when the call has
    ``left`` seconds (``None``: no limit of its own) and the rows with the caps ``later`` are
    still to train after it."""
    if left is None:
        return cap
    share = left - reserve * (1 + len(later)) - sum(c or 0.0 for c in later)
    share = max(share, LEAST)
    return share if cap is None else min(cap, share)


class Schedule:
    """The time limits of the rows a call trains, in ``order`` (the keys of the rows still to
    train), each with its cap in ``caps``, within ``seconds`` of ``started`` (a
    ``time.monotonic()``; ``seconds`` ``None``: no limit of the call's own)."""

    def __init__(self, order: list, caps: dict, seconds: float | None, started: float):
        self.order, self.caps, self.seconds, self.started = order, caps, seconds, started

    def limit(self, key) -> float | None:
        """The time limit of row ``key`` as it starts (:func:`time_limit`)."""
        at = self.order.index(key) + 1 if key in self.order else len(self.order)
        left = None if self.seconds is None else self.seconds - (time.monotonic() - self.started)
        return time_limit(self.caps.get(key), [self.caps[k] for k in self.order[at:]], left)
