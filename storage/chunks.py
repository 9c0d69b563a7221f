"""Direct chunk reads from sharded zarr v3 arrays: the store's fast read path.

zarr-python reads a chunk of a sharded array with several async round trips (shard index,
chunk) and per-call overhead that costs more than decompressing a 400² render. This reader
implements just the codec chain the writer creates, after checking the array's metadata names
exactly that chain: ``sharding_indexed`` (index at the end, codecs ``bytes(little) → zstd →
crc32c``, index codecs ``bytes(little) → crc32c``). It keeps each shard's index once read,
then fetches one byte range per chunk (``pread`` locally, a ranged GET on object stores),
checks its crc32c and decompresses it. Any mismatch raises :class:`StoreError`; a store with
another codec chain is refused here, and ``shards verify`` reads through zarr itself.
"""

from __future__ import annotations

import contextlib
import json
import math
import os
from collections import OrderedDict

import google_crc32c
import numpy as np
from numcodecs import Zstd

from storage.backend import Backend
from storage.errors import StoreError
from storage.retry import retrying

_MISSING = 2**64 - 1
_INDEX_CACHE = 256  # shards whose index is kept, per array


def _expected_chain(meta: dict, where: str) -> tuple[list[int], list[int]]:
    """(shard shape, chunk shape), or raise when the codecs are not the writer's chain."""
    try:
        (codec,) = meta["codecs"]
        conf = codec["configuration"]
        names = [c["name"] for c in conf["codecs"]]
        index_names = [c["name"] for c in conf["index_codecs"]]
        ok = (
            codec["name"] == "sharding_indexed"
            and names == ["bytes", "zstd", "crc32c"]
            and index_names == ["bytes", "crc32c"]
            and conf.get("index_location", "end") == "end"
            and conf["codecs"][0].get("configuration", {}).get("endian", "little") == "little"
            and meta["chunk_key_encoding"].get("configuration", {}).get("separator", "/") == "/"
        )
    except (KeyError, ValueError, TypeError):
        ok = False
    if not ok:
        raise StoreError(f"{where}: array does not use the shard store's codec chain")
    return meta["chunk_grid"]["configuration"]["chunk_shape"], conf["chunk_shape"]


class ChunkReader:
    """Reads chunk ``k`` of shard ``s`` of one sharded array as a numpy array."""

    def __init__(self, backend: Backend, name: str):
        raw = backend.get(f"{name}/zarr.json")
        if raw is None:
            raise StoreError(f"{backend.url}: array {name} is missing")
        meta = json.loads(raw)
        self.backend, self.name = backend, name
        self.shard_shape, self.chunk_shape = _expected_chain(meta, f"{backend.url}/{name}")
        self.dtype = np.dtype(meta["data_type"]).newbyteorder("<")
        self.per_shard = math.prod(
            s // c for s, c in zip(self.shard_shape, self.chunk_shape, strict=True)
        )
        self.fill = meta.get("fill_value", 0)
        self._index: OrderedDict[int, np.ndarray] = OrderedDict()
        self._zstd = Zstd()  # numcodecs': zarr's own zstd, so the reader needs no other package
        self._fds: dict[int, int] = {}

    def _key(self, shard: int) -> str:
        return f"{self.name}/c/" + "/".join([str(shard)] + ["0"] * (len(self.shard_shape) - 1))

    def _read(self, shard: int, start: int, length: int) -> bytes:
        key = self._key(shard)
        if self.backend.local:
            fd = self._fds.get(shard)
            if fd is None:
                fd = os.open(self.backend.path(key), os.O_RDONLY)
                self._fds[shard] = fd
                if len(self._fds) > _INDEX_CACHE:
                    os.close(self._fds.pop(next(iter(self._fds))))
            if start < 0:
                start += os.fstat(fd).st_size
            data = os.pread(fd, length, start)
        else:
            if start < 0:
                start += self.backend.size(key)
            data = self._remote_range(key, start, length)
        if len(data) != length:
            raise StoreError(f"{self.backend.url}: {key} is truncated")
        return data

    @retrying
    def _remote_range(self, key: str, start: int, length: int) -> bytes:
        return self.backend.fs.cat_file(self.backend.path(key), start=start, end=start + length)

    def index(self, shard: int) -> np.ndarray:
        """``(per_shard, 2) uint64``: (offset, nbytes) of each chunk in the shard file."""
        idx = self._index.get(shard)
        if idx is not None:
            self._index.move_to_end(shard)
            return idx
        n = 16 * self.per_shard
        try:
            raw = self._read(shard, -(n + 4), n + 4)
        except (FileNotFoundError, OSError) as exc:
            raise StoreError(f"{self.backend.url}: {self._key(shard)} unreadable ({exc})") from None
        if google_crc32c.value(raw[:n]) != int.from_bytes(raw[n:], "little"):
            raise StoreError(f"{self.backend.url}: {self._key(shard)}: shard index checksum")
        idx = np.frombuffer(raw[:n], "<u8").reshape(-1, 2)
        self._index[shard] = idx
        if len(self._index) > _INDEX_CACHE:
            self._index.popitem(last=False)
        return idx

    def chunk(self, shard: int, k: int) -> np.ndarray:
        """Chunk ``k`` (C order within the shard) of ``shard``, shape ``chunk_shape``."""
        offset, nbytes = (int(x) for x in self.index(shard)[k])
        if offset == _MISSING:
            return np.full(self.chunk_shape, self.fill, self.dtype)
        raw = self._read(shard, offset, nbytes)
        if google_crc32c.value(raw[:-4]) != int.from_bytes(raw[-4:], "little"):
            raise StoreError(f"{self.backend.url}: {self._key(shard)}: chunk {k} checksum")
        try:
            data = self._zstd.decode(raw[:-4])
        except RuntimeError as exc:  # numcodecs raises it for a frame it cannot decode
            raise StoreError(f"{self.backend.url}: {self._key(shard)}: chunk {k}: {exc}") from None
        return np.frombuffer(data, self.dtype).reshape(self.chunk_shape)

    def close(self) -> None:
        for fd in self._fds.values():
            os.close(fd)
        self._fds.clear()

    def __del__(self) -> None:
        with contextlib.suppress(Exception):  # interpreter shutdown
            self.close()
