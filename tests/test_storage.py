"""The shard store: schema, commit protocol, concurrency, corruption, datasets, the CLI."""

from __future__ import annotations

import dataclasses
import json
import multiprocessing as mp
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from storage.catalog import Catalog, draw_heldout, holdout_count
from storage.errors import ShardCommittedError, StoreError
from storage.reader import Store
from storage.schema import (
    Layout,
    commit_key,
    decode_maps,
    encode_maps,
    round_renders,
    untrainable,
)
from storage.writer import create_store, write_shard
from tests.storage_helpers import synthetic_payload

BIN = Path(sys.executable).parent
LAYOUT = Layout(num_materials=7, suns_per_material=3, resolution=16, shard_size=6)


def shards(*args, cwd=None, env=None):
    return subprocess.run(
        [str(BIN / "shards"), *map(str, args)],
        capture_output=True,
        text=True,
        cwd=cwd,
        env=env,
        timeout=120,
    )


def full_store(path, layout=LAYOUT, seed=0):
    store = create_store(str(path), layout, {"samples": 8, "resolution": layout.resolution})
    for shard in range(layout.num_shards):
        write_shard(store, shard, synthetic_payload(layout, shard, seed))
    return store


# ---- layout and encoding (pure) ------------------------------------------------------------


@pytest.mark.parametrize(
    "materials,suns,shard_size", [(1, 1, 1), (7, 3, 6), (10, 5, 25), (11, 5, 50), (3, 2, 200)]
)
def test_layout_partitions_samples_and_materials(materials, suns, shard_size):
    lay = Layout(materials, suns, 16, shard_size)
    samples = [s for sh in range(lay.num_shards) for s in lay.shard_samples(sh)]
    mats = [m for sh in range(lay.num_shards) for m in lay.shard_materials(sh)]
    assert samples == list(range(lay.num_samples)) and mats == list(range(materials))
    for sh in range(lay.num_shards):  # every sample's material lives in the same shard
        assert {lay.material_of_sample(s) for s in lay.shard_samples(sh)} == set(
            lay.shard_materials(sh)
        )
        assert all(lay.shard_of_sample(s) == sh for s in lay.shard_samples(sh))


def test_indices_outside_the_store_are_refused_naming_the_index_asked_for(tmp_path):
    for bad in (-1, LAYOUT.num_samples):
        for find in (LAYOUT.material_of_sample, LAYOUT.shard_of_sample):
            with pytest.raises(IndexError, match=rf"^sample {bad} out of range \(store has 21\)$"):
                find(bad)
    store = full_store(tmp_path / "s.zarr")
    for bad in (-1, 7):
        with pytest.raises(IndexError, match=rf"^material {bad} out of range \(store has 7\)$"):
            store.packed_maps(bad)


def test_shard_size_must_hold_whole_materials():
    with pytest.raises(ValueError, match="multiple of the suns"):
        Layout(4, 5, 16, 12)


@pytest.mark.parametrize(
    "side, says",
    [(16, None), (400, None), (8, "try 16"), (17, "try 16 or 32"), (100, "try 96 or 112")],
)
def test_untrainable_sides_are_named_with_the_nearest_trainable_ones(side, says):
    why = untrainable(side)
    assert why is None if says is None else (f"resolution {side} is not" in why and says in why)
    assert (untrainable(side, nearest=False) is None) == (says is None)


def test_map_encoding_round_trips_within_8_bit_precision():
    rng = np.random.default_rng(0)
    maps = {
        "diffuse": rng.random((3, 8, 8)),
        "specular": rng.random((3, 8, 8)) ** 3,
        "roughness": rng.random((1, 8, 8)),
        "normal": rng.random((3, 8, 8)),
        "mask": rng.random((1, 8, 8)),
    }
    back = decode_maps(encode_maps(maps))
    for name in ("roughness", "normal", "mask"):
        np.testing.assert_allclose(back[name], maps[name], atol=0.5 / 255 + 1e-6)
    # colours are stored sRGB: dark values keep their relative precision
    dark = maps["specular"] < 0.01
    rel = np.abs(back["specular"] - maps["specular"])[~dark] / maps["specular"][~dark]
    assert rel.max() < 0.08


# ---- commit protocol -----------------------------------------------------------------------


def test_renders_rounded_to_fewer_mantissa_bits_are_near_and_compress_better():
    from numcodecs import Zstd

    rng = np.random.default_rng(0)
    renders = rng.gamma(1.0, 0.3, (4, 3, 32, 32)).astype(np.float16)
    renders[0, 0, 0, :3] = [65504, -65504, np.inf]  # past the largest when rounded up; inf
    assert round_renders(renders, 10) is renders
    kept = round_renders(renders, 6)
    assert kept.dtype == np.float16 and kept.shape == renders.shape
    assert not (kept.view(np.uint16) & 0b1111).any()  # the 4 bits dropped are zeros
    finite = np.isfinite(renders) & (np.abs(renders) >= np.finfo(np.float16).smallest_normal)
    err = np.abs(kept[finite].astype(np.float32) / renders[finite].astype(np.float32) - 1)
    assert err.max() <= 2**-7 and err.mean() > 2**-11  # each within half a step; not a copy
    assert kept[0, 0, 0, :2].tolist() == [65024, -65024] and np.isinf(kept[0, 0, 0, 2])
    size = [len(Zstd(level=3).encode(x.tobytes())) for x in (renders, kept)]
    assert size[1] < 0.8 * size[0], size


@pytest.mark.parametrize("bits", [None, 6])
def test_a_shards_renders_keep_the_mantissa_bits_its_stores_settings_name(tmp_path, bits):
    settings = {"samples": 8} | ({} if bits is None else {"render_bits": bits})
    store = create_store(str(tmp_path / "s.zarr"), LAYOUT, settings)
    payload = synthetic_payload(LAYOUT, 0)
    write_shard(store, 0, payload)
    stored = Store(str(tmp_path / "s.zarr")).read_shard(0).renders
    want = payload.renders if bits is None else round_renders(payload.renders, bits)
    np.testing.assert_array_equal(stored, want)
    assert (bits is None) == np.array_equal(stored, payload.renders)


def test_round_trip_of_every_sample(tmp_path):
    store = full_store(tmp_path / "s.zarr")
    again = Store(str(tmp_path / "s.zarr"))
    assert again.committed_shards() == list(range(LAYOUT.num_shards))
    for shard in range(LAYOUT.num_shards):
        p = synthetic_payload(LAYOUT, shard)
        for j, i in enumerate(LAYOUT.shard_samples(shard)):
            x = again.sample(i)
            np.testing.assert_array_equal(x.render, p.renders[j].astype(np.float32))
            m = LAYOUT.material_of_sample(i) - LAYOUT.shard_materials(shard).start
            expect = decode_maps(p.maps[m])
            for name in expect:
                np.testing.assert_array_equal(x.maps[name], expect[name])
            assert x.seed == i and x.material_index == LAYOUT.material_of_sample(i)
            assert x.source_id == f"m{x.material_index}"
    assert store.materials().keys() == set(range(7))


def test_uncommitted_shard_is_invisible_and_rewritable(tmp_path):
    """A writer killed after writing the bytes, before the commit record: nothing shows."""
    path = tmp_path / "s.zarr"
    create_store(str(path), LAYOUT, {})
    code = (
        "import os, storage.backend as b\n"
        "from storage.reader import Store\n"
        "from storage.writer import write_shard\n"
        "from tests.storage_helpers import synthetic_payload\n"
        f"s = Store({str(path)!r})\n"
        "b.Backend.put_atomic = lambda *a, **k: os._exit(9)  # die at the commit\n"
        "write_shard(s, 1, synthetic_payload(s.layout, 1))\n"
    )
    r = subprocess.run([sys.executable, "-c", code], cwd=Path(__file__).parent.parent)
    assert r.returncode == 9
    store = Store(str(path))
    assert store.committed_shards() == [] and store.shard_state(1) == "pending"
    with pytest.raises(StoreError, match="not committed"):
        store.sample(LAYOUT.shard_samples(1).start)
    assert store.commits() == {}
    write_shard(store, 1, synthetic_payload(LAYOUT, 1))  # re-writable
    assert store.committed_shards() == [1]


def test_files_get_the_umask_mode_so_other_users_can_read_them(tmp_path):
    """Commit records, the screen UV layout and job state (atomic writes) get the mode a
    plain ``open`` gives, as zarr's own chunks do: 0o666 less the umask, not mkstemp's 0o600
    (a dashboard or trainer under another uid reads a shared store)."""
    from storage.backend import write_atomic

    umask = os.umask(0o022)
    os.umask(umask)  # read back as it was
    store = full_store(tmp_path / "s.zarr")
    write_atomic(tmp_path / "s.zarr" / "farm" / "job.json", lambda f: f.write(b"{}"))
    files = [p for p in (tmp_path / "s.zarr").rglob("*") if p.is_file()]
    assert len(store.commits()) == LAYOUT.num_shards
    assert any(p.parent.name == "commits" for p in files) and any(
        p.name == "job.json" for p in files
    )
    assert {p.relative_to(tmp_path).as_posix(): oct(p.stat().st_mode & 0o777) for p in files} == {
        p.relative_to(tmp_path).as_posix(): oct(0o666 & ~umask) for p in files
    }
    assert not [p for p in files if p.name.startswith(".")]  # no temporary left


def test_committed_shard_is_not_rewritten_unless_asked(tmp_path):
    store = full_store(tmp_path / "s.zarr")
    with pytest.raises(ShardCommittedError, match="shard 2 is already committed"):
        write_shard(store, 2, synthetic_payload(LAYOUT, 2, seed=5))
    write_shard(store, 2, synthetic_payload(LAYOUT, 2, seed=5), overwrite=True)
    np.testing.assert_array_equal(
        store.sample(12).render, synthetic_payload(LAYOUT, 2, 5).renders[0].astype(np.float32)
    )


def test_bad_payload_is_refused_before_writing(tmp_path):
    store = create_store(str(tmp_path / "s.zarr"), LAYOUT, {})
    p = synthetic_payload(LAYOUT, 0)
    p.renders = p.renders[:, :, :8]
    with pytest.raises(StoreError, match="renders has shape"):
        write_shard(store, 0, p)
    p = synthetic_payload(LAYOUT, 0)
    p.renders[0, 0, 0, 0] = np.nan
    with pytest.raises(StoreError, match="NaN"):
        write_shard(store, 0, p)
    assert store.shard_state(0) == "empty"


def test_existing_store_with_other_settings_is_refused(tmp_path):
    full_store(tmp_path / "s.zarr")
    with pytest.raises(StoreError, match="already exists"):
        create_store(str(tmp_path / "s.zarr"), LAYOUT, {})
    with pytest.raises(StoreError, match=r"settings.samples=8, not 16"):
        create_store(str(tmp_path / "s.zarr"), LAYOUT, {"samples": 16}, exist_ok=True)
    other = Layout(7, 3, 32, 6)
    with pytest.raises(StoreError, match=r"layout.resolution=16, not 32"):
        create_store(str(tmp_path / "s.zarr"), other, {}, exist_ok=True)
    same = create_store(str(tmp_path / "s.zarr"), LAYOUT, {"samples": 8}, exist_ok=True)
    assert len(same.committed_shards()) == LAYOUT.num_shards


def _write_shards(path: str, shards_to_write: list[int]) -> None:
    store = Store(path)
    for shard in shards_to_write:
        write_shard(store, shard, synthetic_payload(store.layout, shard))


def test_concurrent_writers_lose_nothing(tmp_path):
    layout = Layout(num_materials=40, suns_per_material=2, resolution=16, shard_size=4)
    path = str(tmp_path / "s.zarr")
    create_store(path, layout, {})
    ctx = mp.get_context("spawn")
    jobs = [list(range(w, layout.num_shards, 4)) for w in range(4)]
    procs = [ctx.Process(target=_write_shards, args=(path, j)) for j in jobs]
    for p in procs:
        p.start()
    for p in procs:
        p.join(60)
        assert p.exitcode == 0
    store = Store(path)
    assert store.committed_shards() == list(range(layout.num_shards))
    for shard in range(layout.num_shards):
        got, want = store.read_shard(shard), synthetic_payload(layout, shard)
        np.testing.assert_array_equal(got.renders, want.renders)
        np.testing.assert_array_equal(got.maps, want.maps)
        np.testing.assert_array_equal(got.seed, want.seed)
    assert shards("verify", path).returncode == 0


# ---- verify and corruption -----------------------------------------------------------------


def shard_file(path, array, shard):
    return Path(path) / array / "c" / str(shard) / "0" / "0" / "0"


def test_verify_passes_a_sound_store(tmp_path):
    full_store(tmp_path / "s.zarr")
    r = shards("verify", tmp_path / "s.zarr")
    assert r.returncode == 0 and "OK: 4 committed shard(s) checked" in r.stdout


def test_verify_passes_shards_of_material_0_alone_and_finds_their_chunk_deleted(tmp_path):
    """A shard of material 0 alone has an all-zero ``material_index``, zarr's fill value: the
    chunk must still be written, so that verify neither flags it nor misses its loss."""
    path = tmp_path / "m0.zarr"
    full_store(path, Layout(num_materials=3, suns_per_material=2, resolution=16, shard_size=2))
    key = Path(path) / "material_index" / "c" / "0"
    assert key.is_file()
    assert json.loads((path / commit_key(0)).read_text())["files"]["material_index/c/0"] > 0
    r = shards("verify", path)
    assert r.returncode == 0 and "OK: 3 committed shard(s) checked" in r.stdout, r.stdout
    key.unlink()
    r = shards("verify", path)
    assert r.returncode == 1 and "shard 0: material_index/c/0 is missing" in r.stdout


def test_verify_finds_a_single_flipped_byte(tmp_path):
    full_store(tmp_path / "s.zarr")
    f = shard_file(tmp_path / "s.zarr", "renders", 2)
    data = bytearray(f.read_bytes())
    data[len(data) // 3] ^= 0x01
    f.write_bytes(bytes(data))
    r = shards("verify", tmp_path / "s.zarr")
    assert r.returncode == 1
    assert "shard 2: unreadable" in r.stdout and "checksum" in r.stdout
    assert "shard 1" not in r.stdout and "1 bad shard(s)" in r.stdout


def test_verify_finds_truncation_missing_commit_and_bad_values(tmp_path):
    path = tmp_path / "s.zarr"
    full_store(path)
    f = shard_file(path, "maps", 0)
    f.write_bytes(f.read_bytes()[:100])  # truncated
    os.remove(path / commit_key(1))  # commit record lost: data without a commit
    rec = json.loads((path / commit_key(3)).read_text())
    store = Store(str(path))
    p = synthetic_payload(LAYOUT, 3)
    p.turbidity[:] = 42.0  # out of range, written behind the writer's back
    store.backend.open_group("r+")["turbidity"][18:21] = p.turbidity
    rec["files"] = {k: store.backend.size(k) for k in store.shard_keys(3)}
    (path / commit_key(3)).write_text(json.dumps(rec))
    r = shards("verify", path, "--json")
    assert r.returncode == 1
    problems = json.loads(r.stdout)["problems"]
    assert set(problems) == {"0", "1", "3"}
    assert any("commit record says" in x for x in problems["0"])
    assert any("without a commit record" in x for x in problems["1"])
    assert any("turbidity outside" in x for x in problems["3"])


# ---- datasets ------------------------------------------------------------------------------


def test_stores_read_as_one_catalog_split_by_material(tmp_path):
    a, b = full_store(tmp_path / "a.zarr"), full_store(tmp_path / "b.zarr", seed=1)
    urls = [a.url, b.url]
    cat = Catalog.snapshot(urls, seed=0, holdout_fraction=0.25, storage_options=None)
    train, test = cat.split("train"), cat.split("test")
    assert len(train) + len(test) == 2 * LAYOUT.num_samples
    held = {(int(s), LAYOUT.material_of_sample(int(k))) for s, k in test.refs}
    trained = {(int(s), LAYOUT.material_of_sample(int(k))) for s, k in train.refs}
    assert len(held) == round(0.25 * 2 * LAYOUT.num_materials) and held.isdisjoint(trained)
    assert len(test) == len(held) * LAYOUT.suns_per_material  # every sun of a held material
    assert {int(s) for s, _ in train.refs} == {0, 1}  # both stores, as one
    again = Catalog.snapshot(urls, seed=0, holdout_fraction=0.25, storage_options=None)
    assert again.heldout == cat.heldout and cat.repeated == 0
    other = Catalog.snapshot(urls, seed=1, holdout_fraction=0.25, storage_options=None)
    assert other.heldout != cat.heldout
    assert Catalog.snapshot(urls[::-1], 0, 0.25, None).heldout == cat.heldout[::-1]  # any order
    assert Catalog.from_dict(cat.to_dict()) == cat
    recorded = cat.material_sources()
    assert recorded == dataclasses.replace(cat, trained_sources=None).material_sources([a, b])
    assert len(recorded[1]) == len(held) and not recorded[0] & recorded[1]
    with pytest.raises(ValueError, match="cannot hold out 99 of 14"):
        draw_heldout(list(range(14)), 99, 0)


def test_a_material_in_several_stores_is_on_one_side_of_the_split_in_all(tmp_path):
    """``again`` holds ``a``'s materials (a farm job with the same seed), half of them
    committed; ``b`` others."""
    a, b = full_store(tmp_path / "a.zarr"), full_store(tmp_path / "b.zarr", seed=1)
    again = create_store(str(tmp_path / "again.zarr"), LAYOUT, {})
    for shard in range(0, LAYOUT.num_shards, 2):
        write_shard(again, shard, synthetic_payload(LAYOUT, shard))
    copied = [m for shard in again.committed_shards() for m in LAYOUT.shard_materials(shard)]
    copies_held = 0
    for seed in range(6):
        cat = Catalog.snapshot([a.url, again.url, b.url], seed, 0.25, None)
        assert cat.heldout[1] == [m for m in cat.heldout[0] if m in copied]
        copies_held += len(cat.heldout[1])
        assert cat.repeated == len(copied)
        distinct = 2 * LAYOUT.num_materials  # a's and b's: again adds none
        assert len(cat.heldout[0]) + len(cat.heldout[2]) == holdout_count(0.25, range(distinct))
        test = {(int(s), LAYOUT.material_of_sample(int(k))) for s, k in cat.split("test").refs}
        train = {(int(s), LAYOUT.material_of_sample(int(k))) for s, k in cat.split("train").refs}
        assert not {m for s, m in test if s < 2} & {m for s, m in train if s < 2}
    assert copies_held  # the seeds drew some of the copied materials


def test_a_fine_tuned_catalog_keeps_the_split_of_the_run_it_starts_from(tmp_path):
    """Materials are kept on their side by identity, in any store: ``a2`` holds ``a``'s
    materials rendered again (the same seed), ``b`` others."""
    a, a2 = full_store(tmp_path / "a.zarr"), full_store(tmp_path / "a2.zarr")
    b = full_store(tmp_path / "b.zarr", seed=1)
    ids = {m: rec["source_id"] for m, rec in a.materials().items()}
    # the first run saw a's first two shards (a farm still writing) and held one out
    seen = {m for shard in (0, 1) for m in LAYOUT.shard_materials(shard)}
    kept = {min(seen)}
    keep = ({ids[m] for m in seen - kept}, {ids[m] for m in kept})
    unseen = 2 * LAYOUT.num_materials - len(seen)
    draws = set()
    for seed in range(4):
        cat = Catalog.snapshot([a2.url, b.url], seed, 0.3, None, keep=keep)
        assert set(cat.heldout[0]) & seen == kept  # held out stay out, trained stay in
        new = [m for m in cat.heldout[0] if m not in seen] + cat.heldout[1]
        assert len(new) == holdout_count(0.3, range(unseen))  # the rest drawn as ever
        draws.add(tuple(new))
    assert len(draws) > 1  # by the seed
    alone = Catalog.snapshot([b.url], 0, 0.3, None, keep=keep)  # none of the kept in b
    assert keep[0] <= set(alone.trained_sources) and keep[1] <= set(alone.held_sources)
    assert alone.material_sources() == (set(alone.trained_sources), set(alone.held_sources))
    urls = [a.url, b.url]
    assert Catalog.snapshot(urls, 0, 0.3, None, keep=None) == Catalog.snapshot(urls, 0, 0.3, None)
    counts = [(0.25, 14, 4), (0.01, 10, 1), (0.5, 1, 0), (0.99, 3, 2), (0.0, 5, 0), (0.5, 0, 0)]
    assert [holdout_count(f, range(n)) for f, n, _ in counts] == [c for *_, c in counts]


# ---- CLI -----------------------------------------------------------------------------------


def test_ls_info_show_export(tmp_path):
    path = tmp_path / "s.zarr"
    full_store(path)
    r = shards("ls", path, "--json")
    rows = json.loads(r.stdout)
    assert [x["state"] for x in rows] == ["committed"] * 4 and rows[3]["samples"] == 3
    info = json.loads(shards("info", path, "--json").stdout)
    assert info["samples"]["committed"] == 21
    assert info["materials_by_kind"] == {"procedural": 3, "uniform": 4}
    assert sum(h["count"] for h in info["turbidity"]) == 21
    text = shards("info", path).stdout
    assert "sun elevation" in text and "turbidity" in text
    lines = text.splitlines()
    first = next(i for i, line in enumerate(lines) if line.startswith("settings "))
    keys = [line[13:].split()[0] for line in lines[first : first + len(info["settings"])]]
    assert keys == sorted(info["settings"])  # one setting a line
    assert f"{info['bytes']['compression_ratio']:.2f}x" in text
    r = shards("show", path, "--sample", "5", "-o", tmp_path / "s5.png")
    assert r.returncode == 0 and (tmp_path / "s5.png").stat().st_size > 0
    r = shards("export", path, "-o", tmp_path / "png", "--samples", "2:5")
    assert r.returncode == 0
    assert len(list((tmp_path / "png").glob("*_render.png"))) == 3
    r = shards("export", path, "-o", tmp_path / "exr", "--samples", "4", "--format", "exr")
    assert sorted(p.name for p in (tmp_path / "exr").iterdir()) == [
        "sample_000004.json",
        "sample_000004_maps.exr",
        "sample_000004_render.exr",
    ]


def test_cli_bad_input_is_one_line(tmp_path):
    path = tmp_path / "s.zarr"
    full_store(path)
    (tmp_path / "plain").mkdir()
    meta = json.loads((path / "zarr.json").read_text())
    meta["attributes"]["shaderball"]["schema_version"] = 99
    (tmp_path / "v99.zarr").mkdir()
    (tmp_path / "v99.zarr" / "zarr.json").write_text(json.dumps(meta))
    os.remove(path / commit_key(2))
    cases = [
        (["info", tmp_path / "plain"], "not a shard store"),
        (["ls", tmp_path / "v99.zarr"], "unknown schema version 99"),
        (["show", path, "--sample", "999", "-o", tmp_path / "x.png"], "out of range"),
        (["show", path, "--sample", "13", "-o", tmp_path / "x.png"], "not committed"),
        (["export", path, "-o", tmp_path / "e", "--samples", "12:14"], "not committed"),
    ]
    for args, needle in cases:
        r = shards(*args)
        assert r.returncode == 1, (args, r.stderr)
        lines = r.stderr.strip().splitlines()
        assert len(lines) == 1 and needle in lines[0] and "Traceback" not in r.stderr, args
    assert not (tmp_path / "e").exists() or not list((tmp_path / "e").iterdir())
    r = shards("export", path, "-o", tmp_path / "e", "--samples", "9:2")
    assert r.returncode == 2 and "Invalid value for --samples: '9:2' is outside" in r.stderr
    r = shards("export", path, "-o", tmp_path / "e", "--samples", "1:2:3")
    assert r.returncode == 2 and "for --samples: '1:2:3' is not START:STOP" in r.stderr
    r = shards("show", path, "--sample", "5", "-o", tmp_path / "s5.txt")
    assert r.returncode == 2 and "'s5.txt' does not name a picture" in r.stderr.replace(
        str(tmp_path) + "/", ""
    )  # fmt: skip
    assert not (tmp_path / "s5.txt").exists()


def test_fast_reads_match_zarr_and_catch_corruption(tmp_path):
    path = tmp_path / "s.zarr"
    store = full_store(path)
    for shard in range(LAYOUT.num_shards):  # direct chunk reads == zarr's own decode
        whole = store.read_shard(shard)
        for j, i in enumerate(LAYOUT.shard_samples(shard)):
            np.testing.assert_array_equal(store.render(i), whole.renders[j])
    f = shard_file(path, "renders", 1)
    data = bytearray(f.read_bytes())
    data[40] ^= 0x10  # inside the first chunk of shard 1 (sample 6)
    f.write_bytes(bytes(data))
    with pytest.raises(StoreError, match="checksum"):
        Store(str(path)).sample(6)
    r = shards("show", path, "--sample", "6", "-o", tmp_path / "x.png")
    assert r.returncode == 1 and len(r.stderr.strip().splitlines()) == 1
    assert "checksum" in r.stderr and not (tmp_path / "x.png").exists()


def test_a_chunk_whose_checksum_holds_but_whose_zstd_frame_does_not_is_a_store_error(tmp_path):
    import google_crc32c

    from storage.chunks import ChunkReader

    path = tmp_path / "s.zarr"
    store = full_store(path)
    offset, nbytes = (int(x) for x in ChunkReader(store.backend, "renders").index(1)[0])
    f = shard_file(path, "renders", 1)
    data = bytearray(f.read_bytes())
    body = bytes(nbytes - 4)  # zeros: no zstd frame, under a checksum that matches them
    data[offset : offset + nbytes] = body + google_crc32c.value(body).to_bytes(4, "little")
    f.write_bytes(bytes(data))
    with pytest.raises(StoreError, match="renders/c/1/0/0/0: chunk 0: Zstd"):
        Store(str(path)).render(6)
