"""Storage benchmark: bytes per sample, write speed, read speed (sequential / shuffled, 1 and 2
processes) of the zarr shard store against the raw decode bound of its own bytes, MDS
(mosaicml-streaming) and a WebDataset tar, at 400² on this machine, in one run.

    make bench-storage      # builds .venv-bench (MDS needs torchvision), then runs this
    .venv-bench/bin/python -m benchmarks.storage [--samples 200] [--render-spp 32]

Data: real Cycles renders and screen maps of procedural materials (a pool of 4 materials x
2 suns at 400², cached in benchmarks/.cache), repeated to ``--samples`` samples (5 suns a
material). Each chunk compresses on its own, so repetition does not flatter any format.
Every reader ends with the same work: render float16 → float32, maps uint8 → float32 (sRGB
decode of the colours), so the formats differ only in how they fetch and decompress bytes.
MDS and WebDataset store the maps with every sample (they have no per-material table). Each MDS
pass starts from a fresh copy of its compressed shards (it decompresses shards into its local
folder on first touch, which would hand later passes raw files).
"""

from __future__ import annotations

import argparse
import multiprocessing as mp
import shutil
import struct
import tempfile
import time
from pathlib import Path

import numpy as np
from numcodecs import Zstd

from benchmarks.results import Table, save
from render_jobs.materials.procedural import procedural_maps
from render_jobs.process import RenderProcess
from render_jobs.specs import RenderSettings
from render_jobs.sun import sun_from_angles
from storage.reader import Store
from storage.schema import Layout, ShardPayload, decode_maps, encode_maps
from storage.writer import create_store, write_shard

RES = 400
SUNS = 5
CACHE = Path(__file__).parent / ".cache"


def render_pool(spp: int) -> tuple[np.ndarray, np.ndarray]:
    """(maps (4, 11, H, W) uint8, renders (8, 3, H, W) float16) from real Cycles renders."""
    path = CACHE / f"pool-{RES}-{spp}.npz"
    if path.exists():
        z = np.load(path)
        return z["maps"], z["renders"]

    suns = [sun_from_angles(40, 30, 3.0), sun_from_angles(25, 200, 7.0)]
    maps, renders = [], []
    with RenderProcess(RenderSettings(resolution=RES, samples=spp)) as worker:
        for i in range(4):
            print(f"rendering pool material {i + 1}/4 ({RES}², {spp} spp)", flush=True)
            r = worker.render_material(procedural_maps(10 + i, 512), suns, [i, i + 10])
            maps.append(encode_maps(r.maps.as_dict()))
            renders += [x.radiance.astype(np.float16) for x in r.renders]
    CACHE.mkdir(exist_ok=True)
    np.savez(path, maps=np.stack(maps), renders=np.stack(renders))
    return np.stack(maps), np.stack(renders)


def finish(render: np.ndarray, maps: np.ndarray):
    """The decode work every reader ends with."""
    return render.astype(np.float32), decode_maps(maps)


def naive_bytes() -> int:
    return (11 + 3) * RES * RES * 4


def payload(layout: Layout, shard: int, maps_pool, renders_pool) -> ShardPayload:
    s, m = layout.shard_samples(shard), layout.shard_materials(shard)
    return ShardPayload(
        maps=maps_pool[[i % len(maps_pool) for i in m]],
        renders=renders_pool[[i % len(renders_pool) for i in s]],
        material_index=np.repeat(np.asarray(m, np.int32), SUNS),
        sun_direction=np.tile(np.array([0, 0.6, 0.8], np.float32), (len(s), 1)),
        turbidity=np.full(len(s), 3, np.float32),
        seed=np.arange(s.start, s.stop, dtype=np.int64),
        render_seconds=np.ones(len(s), np.float32),
        materials=[{"kind": "procedural", "source_id": f"p{i}", "spec": {}} for i in m],
    )


# ---- readers (module level: picklable for process pools) ------------------------------------

_store = None


def _zarr_init(url):
    global _store
    _store = Store(url)


def _zarr_read(indices):
    for i in indices:
        x = _store.sample(int(i))
        assert x.render.dtype == np.float32
    return len(indices)


def zarr_python_read(url: str, layout: Layout) -> float:
    """Samples/s reading each sample through zarr-python's own array API (no shortcuts)."""
    g = Store(url).group
    t0 = time.perf_counter()
    for i in range(layout.num_samples):
        render = g["renders"][i]
        maps = g["maps"][layout.material_of_sample(i)]
        for name in ("sun_direction", "turbidity", "seed", "render_seconds"):
            g[name][i]
        finish(render, maps)
    return layout.num_samples / (time.perf_counter() - t0)


def timed_pool(init, initargs, fn, parts, processes):
    """Samples/s of ``fn`` over ``parts`` in ``processes`` processes, their start included.

    Forked, as the MDS and WebDataset DataLoaders below are (the Linux default), so that every
    format's time is its reading, not a spawned worker's imports (seconds, against a pass of
    about 2 s here); the trainer spawns its workers (``trainer.training.data.WORKER_START``) and
    pays that once a run."""
    t0 = time.perf_counter()
    if processes == 1:
        init(*initargs)
        n = sum(fn(p) for p in parts)
    else:
        with mp.get_context("fork").Pool(processes, init, initargs) as pool:
            n = sum(pool.map(fn, parts))
    return n / (time.perf_counter() - t0)


def zarr_reads(url, n, seed):
    order = {"seq": np.arange(n), "shuf": np.random.default_rng(seed).permutation(n)}
    out = {}
    for name, idx in order.items():
        for procs in (1, 2):
            parts = np.array_split(idx, procs * 4)
            out[f"{name}{procs}"] = timed_pool(_zarr_init, (url,), _zarr_read, parts, procs)
    return out


def raw_bound(root: Path, layout: Layout) -> float:
    """Samples/s decoding the store's own chunk bytes straight from its shard files."""
    zstd = Zstd()
    t0 = time.perf_counter()
    count = 0
    for shard in range(layout.num_shards):
        chunks = {}
        for name, per in (("renders", layout.shard_size), ("maps", layout.materials_per_shard)):
            data = (root / name / "c" / str(shard) / "0" / "0" / "0").read_bytes()
            index = data[-(16 * per + 4) : -4]
            spans = struct.unpack(f"<{2 * per}Q", index)
            chunks[name] = [
                data[spans[2 * k] : spans[2 * k] + spans[2 * k + 1] - 4] for k in range(per)
            ]
        maps = [
            np.frombuffer(zstd.decode(c), np.uint8).reshape(11, RES, RES) for c in chunks["maps"]
        ]
        for k, c in enumerate(chunks["renders"]):
            render = np.frombuffer(zstd.decode(c), np.float16).reshape(3, RES, RES)
            finish(render, maps[k // SUNS])
            count += 1
    return count / (time.perf_counter() - t0)


def _drain(loader, render_key: str, maps_key: str) -> float:
    """Samples/s of one pass over ``loader``, each sample finished like every reader's."""
    t0 = time.perf_counter()
    k = 0
    for s in loader:
        finish(np.asarray(s[render_key]), np.asarray(s[maps_key]))
        k += 1
    return k / (time.perf_counter() - t0)


def mds_bench(root: Path, n, maps_pool, renders_pool, seed):
    from streaming import MDSWriter, StreamingDataset
    from streaming.base.util import clean_stale_shared_memory
    from torch.utils.data import DataLoader

    out = root / "mds"
    columns = {"render": "ndarray:float16", "maps": "ndarray:uint8"}
    raw = 0
    t0 = time.perf_counter()
    with MDSWriter(out=str(out), columns=columns, compression="zstd:3", size_limit=64 << 20) as w:
        for i in range(n):
            r, m = renders_pool[i % len(renders_pool)], maps_pool[(i // SUNS) % len(maps_pool)]
            w.write({"render": r, "maps": m})
            raw += r.nbytes + m.nbytes
    write = raw / (time.perf_counter() - t0) / 2**20
    stored = sum(f.stat().st_size for f in out.glob("*.mds*"))
    res = {}
    for name, shuffle in (("seq", False), ("shuf", True)):
        for procs in (1, 2):
            clean_stale_shared_memory()
            # a fresh copy of the compressed shards: streaming decompresses a shard into its
            # local folder on first touch, and a later pass would read those raw files
            local = root / f"mds-{name}{procs}"
            shutil.copytree(out, local)
            ds = StreamingDataset(
                local=str(local), shuffle=shuffle, shuffle_seed=seed, batch_size=1
            )
            loader = DataLoader(
                ds, batch_size=None, num_workers=0 if procs == 1 else procs, collate_fn=lambda x: x
            )
            res[f"{name}{procs}"] = _drain(loader, "render", "maps")
            del loader, ds
    return stored / n, write, res


def _wds_iter(urls, shuffle):
    import webdataset as wds

    ds = wds.WebDataset(urls, shardshuffle=False, empty_check=False).decode()
    return ds.shuffle(64) if shuffle else ds


def wds_bench(root: Path, n, maps_pool, renders_pool):
    import webdataset as wds
    from torch.utils.data import DataLoader

    out = root / "wds"
    out.mkdir()
    per_tar = max(1, n // 8)
    raw = 0
    t0 = time.perf_counter()
    for t in range(0, n, per_tar):
        with wds.TarWriter(str(out / f"part-{t // per_tar:04d}.tar")) as w:
            for i in range(t, min(n, t + per_tar)):
                r, m = renders_pool[i % len(renders_pool)], maps_pool[(i // SUNS) % len(maps_pool)]
                w.write({"__key__": f"{i:06d}", "render.npy": r, "maps.npy": m})
                raw += r.nbytes + m.nbytes
    write = raw / (time.perf_counter() - t0) / 2**20
    urls = [str(p) for p in sorted(out.glob("*.tar"))]
    stored = sum(p.stat().st_size for p in out.glob("*.tar"))
    res = {}
    for name, shuffle in (("seq", False), ("shuf", True)):
        for procs in (1, 2):
            ds = _wds_iter(urls, shuffle)
            if procs > 1:
                ds = ds.compose(wds.split_by_worker) if hasattr(ds, "compose") else ds
            loader = DataLoader(ds, batch_size=None, num_workers=0 if procs == 1 else procs)
            res[f"{name}{procs}"] = _drain(loader, "render.npy", "maps.npy")
    return stored / n, write, res


def zarr_rows(url: str, layout: Layout, pools, seed: int) -> list[tuple]:
    """The shard store's row (written here from ``pools``, then read), the raw decode bound's
    and zarr-python's reads: ``(format, bytes a sample, write MB/s, {read: samples/s})``."""
    maps_pool, renders_pool = pools
    n = layout.num_samples
    store = create_store(url, layout, {})
    raw = 0
    t0 = time.perf_counter()
    for shard in range(layout.num_shards):
        p = payload(layout, shard, maps_pool, renders_pool)
        write_shard(store, shard, p)
        raw += p.renders.nbytes + p.maps.nbytes
    write = raw / (time.perf_counter() - t0) / 2**20
    stored = sum(store.shard_bytes(s) for s in range(layout.num_shards)) / n
    return [
        ("zarr shard store", stored, write, zarr_reads(url, n, seed)),
        ("raw decode bound", stored, None, {"seq1": raw_bound(Path(url), layout)}),
        ("zarr-python reads", stored, None, {"seq1": zarr_python_read(url, layout)}),
    ]


def other_rows(root: Path, n: int, pools, seed: int) -> list[tuple]:
    """MDS's and WebDataset's rows, or a row that says which is not installed."""
    rows = []
    for name, bench in (
        ("MDS (streaming)", lambda: mds_bench(root, n, *pools, seed)),
        ("WebDataset tar", lambda: wds_bench(root, n, *pools)),
    ):
        try:
            rows.append((name, *bench()))
        except ImportError as exc:
            rows.append((f"{name}: not installed ({exc.name})", None, None, {}))
    return rows


def print_report(n: int, rows: list[tuple]) -> None:
    """The table of ``rows``, then each target's ratio."""

    def f(x, fmt):
        return format(x, fmt) if x is not None else "-"

    print(
        f"\n{n} samples at {RES}², {mp.cpu_count()} CPUs; naive float32 maps+render per "
        f"sample = {naive_bytes() / 2**20:.2f} MB"
    )
    head = (
        f"{'format':<20}{'MB/sample':>10}{'vs naive':>9}{'write MB/s':>11}"
        f"{'seq 1p':>8}{'shuf 1p':>8}{'seq 2p':>8}{'shuf 2p':>8}   (samples/s)"
    )
    print(head)
    print("-" * len(head))
    for name, per, w, r in rows:
        ratio = f"1/{naive_bytes() / per:.1f}" if per else "-"
        print(
            f"{name:<20}{f(per and per / 2**20, '.3f'):>10}{ratio:>9}{f(w, '.0f'):>11}"
            + "".join(f"{f(r.get(k), '.1f'):>8}" for k in ("seq1", "shuf1", "seq2", "shuf2"))
        )
    z, b = rows[0][3], rows[1][3]["seq1"]
    print(f"\nzarr sequential read / raw decode bound = {z['seq1'] / b:.0%} (target >= 80%)")
    print(f"stored / naive = 1/{naive_bytes() / rows[0][1]:.1f} (target <= 1/4)")
    for name, _, _, r in rows[3:]:
        if r:
            print(
                f"zarr / {name} sequential 1p = {z['seq1'] / r['seq1']:.2f}x, "
                f"shuffled 1p = {z['shuf1'] / r['shuf1']:.2f}x (target >= 1 vs MDS)"
            )
    print("WebDataset 'shuffled' is a 64-sample buffer shuffle over sequential tar reads.")
    table = Table(
        title=f"Storage (`make bench-storage`): {n} samples at {RES}²",
        columns=["format", "MB/sample", "vs naive", "write MB/s", "seq 1p", "shuf 1p",
                 "seq 2p", "shuf 2p"],
        notes=["reads in samples/s, one process (1p) or two (2p), sequential or shuffled; "
               f"naive: float32 maps and render a sample, {naive_bytes() / 2**20:.2f} MB; "
               f"zarr sequential against the raw decode bound {z['seq1'] / b:.0%} (target at "
               "least 80 %)"],
    )  # fmt: skip
    for name, per, w, r in rows:
        table.rows.append(
            [name, per and round(per / 2**20, 3),
             f"1/{naive_bytes() / per:.1f}" if per else None, w and round(w),
             *(r.get(k) and round(r[k], 1) for k in ("seq1", "shuf1", "seq2", "shuf2"))]
        )  # fmt: skip
    save("storage", table)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--samples", type=int, default=200, help="samples (5 suns a material)")
    ap.add_argument("--render-spp", type=int, default=32, help="spp of the cached real renders")
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args()
    n = args.samples - args.samples % SUNS
    pools = render_pool(args.render_spp)
    layout = Layout(num_materials=n // SUNS, suns_per_material=SUNS, resolution=RES, shard_size=25)
    root = Path(tempfile.mkdtemp(prefix="bench-storage-"))
    try:
        rows = zarr_rows(str(root / "set.zarr"), layout, pools, args.seed)
        rows += other_rows(root, n, pools, args.seed)
    finally:
        shutil.rmtree(root, ignore_errors=True)
    print_report(n, rows)


if __name__ == "__main__":
    main()
