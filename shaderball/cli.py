"""The click group of every shaderball CLI (``farm``, ``shards``, ``trainer``).

A :class:`shaderball.errors.UserError` that reaches it ends the command in one line, its
message; so does an ``OSError`` (a store out of reach after its retries, no such bucket,
access denied, a full disk), named by its type. Commands therefore let the errors they expect
rise rather than catch each kind. A closed pipe (``| head``) is left to click, which exits
quietly. The settings every command reads from the environment are checked before it starts
(:func:`shaderball.progress.log_seconds`), so a bad one stops it before it writes anything.
"""

from __future__ import annotations

import errno

import click

from shaderball.errors import UserError
from shaderball.progress import log_seconds


class Commands(click.Group):
    def invoke(self, ctx: click.Context):
        try:
            log_seconds()
            return super().invoke(ctx)
        except UserError as exc:
            raise click.ClickException(str(exc)) from None
        except OSError as exc:
            if exc.errno == errno.EPIPE:
                raise
            raise click.ClickException(f"{type(exc).__name__}: {exc}") from None


def human_bytes(n: float) -> str:
    """``n`` bytes as a CLI prints them: ``512 B``, ``1.5 KB``, ``64.0 MB`` (powers of 1024)."""
    for unit in ("B", "KB", "MB", "GB", "TB"):
        if abs(n) < 1024 or unit == "TB":
            return f"{n:.1f} {unit}" if unit != "B" else f"{int(n)} B"
        n /= 1024
    return str(n)
