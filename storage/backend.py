"""Where a store lives: a local folder or an object-store URL (``s3://...`` via fsspec).

Besides the zarr store itself, a backend gives the few raw operations the commit protocol
needs: an atomic put (local: temp file + fsync + ``os.replace`` + directory fsync; object
stores: one PUT, which is atomic), listing, sizes, and fsync of files zarr wrote. Each
raw operation retries transient object-store errors (:mod:`storage.retry`).
"""

from __future__ import annotations

import os
import secrets
from collections.abc import Callable
from pathlib import Path
from typing import BinaryIO

import zarr
from zarr.storage import FsspecStore, LocalStore

from storage.retry import retrying


def is_remote(url: str) -> bool:
    return "://" in str(url) and not str(url).startswith("file://")


class Backend:
    """Raw access under a store's root; keys are '/'-separated paths relative to it."""

    def __init__(self, url: str | Path, storage_options: dict | None = None):
        self.url = str(url)
        self.storage_options = storage_options or {}
        if is_remote(self.url):
            import fsspec

            self.fs, self.root = fsspec.core.url_to_fs(self.url, **self.storage_options)
            self.local = False
        else:
            self.root = str(Path(self.url.removeprefix("file://")).absolute())
            self.fs = None
            self.local = True

    def zarr_store(self, read_only: bool = False):
        if self.local:
            return LocalStore(self.root, read_only=read_only)
        return FsspecStore.from_url(
            self.url, storage_options=self.storage_options, read_only=read_only
        )

    @retrying
    def open_group(self, mode: str = "r"):
        return zarr.open_group(self.zarr_store(read_only=mode == "r"), mode=mode, zarr_format=3)

    def path(self, key: str) -> str:
        return f"{self.root}/{key}"

    @retrying
    def get(self, key: str) -> bytes | None:
        try:
            if self.local:
                return Path(self.path(key)).read_bytes()
            return self.fs.cat_file(self.path(key))
        except (FileNotFoundError, IsADirectoryError, NotADirectoryError):
            return None

    @retrying
    def size(self, key: str) -> int | None:
        try:
            if self.local:
                return os.path.getsize(self.path(key))
            return int(self.fs.size(self.path(key)))
        except (FileNotFoundError, NotADirectoryError):
            return None

    @retrying
    def listdir(self, key: str) -> list[str]:
        try:
            if self.local:
                return sorted(os.listdir(self.path(key)))
            self.fs.invalidate_cache(self.path(key))  # commits appear from other writers
            return sorted(p.rsplit("/", 1)[-1] for p in self.fs.ls(self.path(key), detail=False))
        except (FileNotFoundError, NotADirectoryError):
            return []

    @retrying
    def put_atomic(self, key: str, data: bytes) -> None:
        """Readers see the old object or the whole new one, never a part."""
        if not self.local:
            self.fs.pipe_file(self.path(key), data)
            return
        write_atomic(self.path(key), lambda f: f.write(data))

    @retrying
    def delete(self, key: str) -> None:
        if self.local:
            Path(self.path(key)).unlink(missing_ok=True)
            _fsync_dir(Path(self.path(key)).parent)
        elif self.fs.exists(self.path(key)):
            self.fs.rm_file(self.path(key))

    def make_durable(self, keys: list[str]) -> None:
        """fsync files zarr wrote (object stores are durable once the PUT returns)."""
        if not self.local:
            return
        dirs = set()
        for key in keys:
            p = Path(self.path(key))
            if p.exists():
                fd = os.open(p, os.O_RDONLY)
                try:
                    os.fsync(fd)
                finally:
                    os.close(fd)
                dirs.add(p.parent)
        for d in dirs:
            _fsync_dir(d)


def _fsync_dir(path: Path) -> None:
    fd = os.open(path, os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


def create_beside(target: Path, suffix: str = "") -> tuple[int, Path]:
    """A new empty file beside ``target``, under a random hidden name, open for writing:
    ``(fd, path)``. Its mode is what a plain ``open`` gives (0o666 less the umask), so that
    other users of a shared folder (a dashboard or trainer under another uid) can read what
    it becomes; ``tempfile.mkstemp`` would make it 0o600."""
    for _ in range(100):
        tmp = target.parent / f".{target.name}.{secrets.token_hex(4)}{suffix}"
        try:
            return os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o666), tmp
        except FileExistsError:
            continue
    raise FileExistsError(f"no free temporary name beside {target}")


def write_atomic(path: str | os.PathLike, write: Callable[[BinaryIO], object]) -> None:
    """Create or replace the local file ``path`` so that readers see the old file or the whole
    new one, never a part, even across a crash: ``write(f)`` fills a temporary file beside it
    (:func:`create_beside`), which is fsynced, renamed over ``path`` (``os.replace``), and its
    folder fsynced."""
    target = Path(path)
    target.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = create_beside(target)
    try:
        with os.fdopen(fd, "wb") as f:
            write(f)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, target)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise
    _fsync_dir(target.parent)
