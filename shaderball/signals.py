"""SIGTERM (a deleted pod, ``timeout``, ``docker stop``) unwinding a command as Ctrl-C does:
its ``finally`` blocks run, so a job saves its state and a preview or an export removes its
temporary folder. No Ray here.

A command opts in (``farm submit``, ``farm preview``, ``shards export``); the CLIs do not
turn it on for every command, because torchrun's ranks (``trainer train``) must die at the
agent's SIGTERM even when blocked in a collective, where a Python handler would run only
after it returns."""

from __future__ import annotations

import contextlib
import signal
import sys
import threading

import click

_TERMINATED = threading.Event()


def _on_sigterm(signum, frame) -> None:
    signal.signal(signal.SIGTERM, signal.SIG_DFL)  # a second SIGTERM kills at once
    _TERMINATED.set()
    # the one exception Ray's blocking calls (ray.wait, ray.get) let through from a handler
    raise KeyboardInterrupt


def stop_on_sigterm() -> None:
    """Make SIGTERM unwind this process's command as Ctrl-C does (a ``KeyboardInterrupt``),
    with :func:`terminated` true after. A farm job calls it when it starts and again after
    ``ray.init``: Ray's core worker installs its own SIGTERM handler there, which ends the
    process at once and leaves the job state saying "running"."""
    if threading.current_thread() is threading.main_thread():
        signal.signal(signal.SIGTERM, _on_sigterm)


@contextlib.contextmanager
def sigterm_held():
    """Hold a SIGTERM that lands in the block (a job's clean-up: workers stopped, state
    saved, Ray shut down) until the block is done, then stop as it asks. With the job's
    handler gone (a first SIGTERM stopped the job), a second one kills at once as before."""
    if threading.current_thread() is not threading.main_thread() or (
        signal.getsignal(signal.SIGTERM) is not _on_sigterm
    ):
        yield
        return
    held = []
    signal.signal(signal.SIGTERM, lambda signum, frame: held.append(signum))
    try:
        yield
    finally:
        signal.signal(signal.SIGTERM, _on_sigterm)
    if held:
        _on_sigterm(signal.SIGTERM, None)


def terminated() -> bool:
    """Whether the ``KeyboardInterrupt`` that stopped a command came from SIGTERM."""
    return _TERMINATED.is_set()


def exit_stopped(kept: str) -> None:
    """Exit as a shell does for the signal that stopped the command (128 + its number),
    after one line: which signal, and what of the work is kept."""
    sig = signal.SIGTERM if terminated() else signal.SIGINT
    click.echo(f"\n{sig.name}: stopped; {kept}", err=True)
    sys.exit(128 + sig)
