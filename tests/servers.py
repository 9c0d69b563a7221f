"""The project's servers (``farm dashboard``, ``trainer viewer``) as real subprocesses."""

from __future__ import annotations

import os
import re
import select
import signal
import subprocess
import time


class ServerProcess:
    """A server command run with ``--port 0``: the port is the one it names in its line
    ``NAME: http://HOST:PORT/``, printed once it listens, so no two servers race for a port."""

    def __init__(
        self, cmd: list, name: str, env: dict | None = None, timeout: float = 60, cwd=None
    ):
        self.name = name
        self.proc = subprocess.Popen(
            [*map(str, cmd), "--port", "0"],
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            env=env,
            cwd=cwd,
        )
        self.early = b""  # stderr up to and with the line that names the port
        self.port = self._wait_for_port(timeout)
        self.base = f"http://127.0.0.1:{self.port}"

    def _wait_for_port(self, timeout: float) -> int:
        pattern = re.compile(rf"^{self.name}: http://\S+:(\d+)/$", re.M)
        fd = self.proc.stderr.fileno()
        deadline = time.time() + timeout
        while time.time() < deadline:
            if not select.select([fd], [], [], 0.5)[0]:
                continue
            chunk = os.read(fd, 65536)
            self.early += chunk
            found = pattern.search(self.early.decode(errors="replace"))
            if found:
                return int(found.group(1))
            if not chunk:
                break  # stderr closed: the server ended
        _, err = self.stop()
        raise AssertionError(f"{self.name} did not start: {err}")

    def stop(self) -> tuple[str, str]:
        """Interrupt it as Ctrl-C does; its stdout and its whole stderr."""
        self.proc.send_signal(signal.SIGINT)
        try:
            out, err = self.proc.communicate(timeout=15)
        except subprocess.TimeoutExpired:
            self.proc.kill()
            out, err = self.proc.communicate()
        return out.decode(), (self.early + err).decode()

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.stop()
