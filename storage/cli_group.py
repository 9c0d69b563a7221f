"""The click group of every shaderball CLI (``farm``, ``shards``, ``trainer``).

An ``OSError`` that reaches it (a store out of reach after its retries, no such bucket,
access denied, a full disk) or a bad environment setting (:class:`SettingError`) ends the
command in one line naming the error, as the errors a command expects do; a closed pipe
(``| head``) is left to click, which exits quietly.
"""

from __future__ import annotations

import errno

import click

from storage.errors import SettingError


class Commands(click.Group):
    def invoke(self, ctx: click.Context):
        try:
            return super().invoke(ctx)
        except OSError as exc:
            if exc.errno == errno.EPIPE:
                raise
            raise click.ClickException(f"{type(exc).__name__}: {exc}") from None
        except SettingError as exc:
            raise click.ClickException(str(exc)) from None


def human_bytes(n: float) -> str:
    """``n`` bytes as a CLI prints them: ``512 B``, ``1.5 KB``, ``64.0 MB`` (powers of 1024)."""
    for unit in ("B", "KB", "MB", "GB", "TB"):
        if abs(n) < 1024 or unit == "TB":
            return f"{n:.1f} {unit}" if unit != "B" else f"{int(n)} B"
        n /= 1024
    return str(n)


def check_picture_name(path, option: str, animated: bool = False) -> None:
    """A usage error naming ``option``, before any work, when ``path`` (``None``: none given)
    names no picture format the CLIs write (:func:`storage.image_files.image_format`)."""
    from storage.image_files import image_format

    try:
        if path is not None:
            image_format(path, animated)
    except ValueError as exc:
        raise click.BadParameter(str(exc), param_hint=option) from None
