"""The click group of every shaderball CLI (``farm``, ``shards``, ``trainer``).

A :class:`shaderball.errors.UserError` that reaches it ends the command in one line, its
message; so does an ``OSError``: the system's own (``[Errno 17] File exists: 'path'``) as
it reads, any other (a store out of reach after its retries, no such bucket, access denied)
named by its type. Commands therefore let the errors they expect
rise rather than catch each kind. A closed pipe (``| head``) is left to click, which exits
quietly.
"""

from __future__ import annotations

import errno

import click

from shaderball.errors import UserError


class Commands(click.Group):
    def invoke(self, ctx: click.Context):
        try:
            return super().invoke(ctx)
        except UserError as exc:
            raise click.ClickException(str(exc)) from None
        except OSError as exc:
            if exc.errno == errno.EPIPE:
                raise
            raise click.ClickException(os_error_line(exc)) from None


def os_error_line(exc: OSError) -> str:
    """An ``OSError`` in one line: an errno-numbered one says what and where itself; another
    (a library's, such as a store's) is named by its type."""
    text = str(exc)
    return text if text.startswith("[Errno ") else f"{type(exc).__name__}: {text}"


def human_bytes(n: float) -> str:
    """``n`` bytes as a CLI prints them: ``512 B``, ``1.5 KB``, ``64.0 MB`` (powers of 1024)."""
    for unit in ("B", "KB", "MB", "GB", "TB"):
        if abs(n) < 1024 or unit == "TB":
            return f"{n:.1f} {unit}" if unit != "B" else f"{int(n)} B"
        n /= 1024
    return str(n)
