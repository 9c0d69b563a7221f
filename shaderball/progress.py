"""Progress bars that suit where they are read: every CLI's bars are made by :func:`bar`.

On a terminal it is tqdm's bar as it is. Elsewhere (a pod's log under Kubernetes, a file, a
pipe) a bar's carriage-return redraws would pile up on one endless line, so there the same
bar prints its whole line (count, percentage, elapsed, remaining, rate and postfix), ending
in a newline, every :data:`PLAIN_EVERY` seconds at most (``SHADERBALL_PROGRESS_S`` sets
another) and once more as it closes, from that many seconds on: work done sooner writes no
line at all.

tqdm is kept rather than a hand-written counter (it has the rates, the remaining time and the
postfix); only the stream it writes to is adapted: :class:`_Lines` turns each redraw into a
line of its own and drops the blank ones tqdm writes to clear it.
"""

from __future__ import annotations

import math
import os
import sys

from tqdm import tqdm

from shaderball.errors import UserError

#: seconds between the lines of a bar that does not write to a terminal, unless EVERY_ENV says
PLAIN_EVERY = 30.0
#: the environment variable that sets those seconds (0: a line at every redraw)
EVERY_ENV = "SHADERBALL_PROGRESS_S"


def log_seconds() -> float:
    """Seconds between a log's bar lines: :data:`EVERY_ENV`, else :data:`PLAIN_EVERY`."""
    value = os.environ.get(EVERY_ENV, "")
    if value == "":
        return PLAIN_EVERY
    try:
        seconds = float(value)
    except ValueError:
        seconds = -1.0
    if not 0 <= seconds < math.inf:
        raise UserError(f"{EVERY_ENV}={value!r}: expected a number of seconds, 0 or more")
    return seconds


class _Lines:
    """A stream for tqdm that writes each redraw as a line of its own."""

    def __init__(self, stream):
        self.stream = stream

    def write(self, s: str) -> None:
        line = s.strip("\r\n")
        if line.strip():
            self.stream.write(line + "\n")

    def flush(self) -> None:
        self.stream.flush()


class _LogBar(tqdm):
    """tqdm drawn into :class:`_Lines` no more often than its ``mininterval``: a new postfix or
    description waits for the next line instead of drawing one of its own."""

    def set_postfix(self, ordered_dict=None, refresh=True, **kwargs):
        super().set_postfix(ordered_dict, refresh=False, **kwargs)

    def set_description(self, desc=None, refresh=True):
        super().set_description(desc, refresh=False)


def on_terminal(stream) -> bool:
    isatty = getattr(stream, "isatty", None)
    try:
        return bool(isatty and isatty())
    except ValueError:  # a closed stream
        return False


def bar(iterable=None, *, file=None, disable: bool = False, **kwargs) -> tqdm:
    """``tqdm(iterable, **kwargs)`` writing to ``file`` (default stderr): on a terminal as
    tqdm draws it, elsewhere as a line every :func:`log_seconds` seconds (the module's
    docstring). ``disable`` shows nothing (another rank's bar, ``--json`` output)."""
    stream = file if file is not None else sys.stderr
    if disable or on_terminal(stream):
        return tqdm(iterable, file=stream, disable=disable, **kwargs)
    seconds = log_seconds()
    # nothing for work done within the first interval: a log gets no 0 % line of a short bar
    every = {"mininterval": seconds, "maxinterval": seconds, "delay": seconds}
    return _LogBar(iterable, file=_Lines(stream), ascii=True, **{**kwargs, **every})
