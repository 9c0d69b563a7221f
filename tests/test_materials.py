"""Material sources: uniform, procedural, SVBRDF files, and every bad-input case."""

import numpy as np
import pytest
from PIL import Image

from render_jobs.errors import MaterialError
from render_jobs.materials import load_maps, parse_source, specs_from_sources
from render_jobs.materials.maps import MAP_CHANNELS, MapBytes
from render_jobs.materials.procedural import PATTERNS, procedural_maps
from render_jobs.materials.uniform import sample_uniform, uniform_maps


def save(path, arr, mode=None):
    Image.fromarray(arr, mode=mode).save(path)
    return path


def panel_png(path, size=16, panels=5, channels=3):
    rng = np.random.default_rng(0)
    shape = (size, size * panels) + ((channels,) if channels > 1 else ())
    arr = rng.integers(0, 256, size=shape, dtype=np.uint8)
    if channels >= 3:  # make the roughness panel (4th) grey
        arr[:, 3 * size : 4 * size, 1] = arr[:, 3 * size : 4 * size, 0]
        arr[:, 3 * size : 4 * size, 2] = arr[:, 3 * size : 4 * size, 0]
    return save(path, arr)


def map_folder(folder, size=16, **override):
    folder.mkdir()
    rng = np.random.default_rng(1)
    files = {
        "wood_basecolor.png": rng.integers(0, 256, (size, size, 3), dtype=np.uint8),
        "wood_specular.png": rng.integers(0, 256, (size, size, 3), dtype=np.uint8),
        "wood_roughness.png": rng.integers(0, 256, (size, size), dtype=np.uint8),
        "wood_normal.png": rng.integers(0, 256, (size, size, 3), dtype=np.uint8),
    }
    files.update(override)
    for name, arr in files.items():
        if arr is not None:
            save(folder / name, arr)
    return folder


# ---- uniform -------------------------------------------------------------------------------


def test_uniform_maps_are_constant_and_in_range():
    for seed in range(20):
        v = sample_uniform(np.random.default_rng(seed))
        m = uniform_maps(v)
        for name in ("diffuse", "specular", "roughness", "normal"):
            arr = getattr(m, name)
            assert np.ptp(arr.reshape(-1, arr.shape[2]), axis=0).max() == 0
        assert 0.05 <= v.roughness <= 1.0
        assert 0.0 <= v.normal_tilt_deg <= 15.0
        n = m.normal[0, 0] * 2 - 1
        assert abs(np.linalg.norm(n) - 1) < 1e-5 and n[2] >= np.cos(np.radians(15)) - 1e-6


# ---- procedural ----------------------------------------------------------------------------


def test_procedural_is_seeded_and_varied():
    a, b = procedural_maps(3, 64), procedural_maps(3, 64)
    for name in ("diffuse", "specular", "roughness", "normal"):
        np.testing.assert_array_equal(getattr(a, name), getattr(b, name))
    c = procedural_maps(4, 64)
    assert not np.array_equal(a.diffuse, c.diffuse)
    kinds = {procedural_maps(s, 32).source_id.rsplit(":", 1)[1] for s in range(40)}
    assert kinds == set(PATTERNS)


def test_procedural_any_resolution_is_the_same_material():
    small, large = procedural_maps(11, 64), procedural_maps(11, 256)
    assert small.diffuse.shape == (64, 64, 3) and large.roughness.shape == (256, 256, 1)
    down = large.diffuse.reshape(64, 4, 64, 4, 3).mean(axis=(1, 3))
    assert np.corrcoef(down.ravel(), small.diffuse.ravel())[0, 1] > 0.9


def test_procedural_tiles_without_seams():
    for seed in range(8):
        m = procedural_maps(seed, 128)
        for arr in (m.diffuse, m.roughness, m.normal):
            seam = np.abs(arr[:, 0] - arr[:, -1]).mean() + np.abs(arr[0] - arr[-1]).mean()
            inner = np.abs(arr[:, 64] - arr[:, 63]).mean() + np.abs(arr[64] - arr[63]).mean()
            assert seam <= 3 * inner + 1e-3, f"seed {seed}: a seam shows at the wrap"


def test_procedural_normals_are_unit_and_upward():
    n = procedural_maps(2, 64).normal * 2 - 1
    np.testing.assert_allclose(np.linalg.norm(n, axis=-1), 1.0, atol=1e-5)
    assert n[..., 2].min() > 0


# ---- SVBRDF files --------------------------------------------------------------------------


def test_panel_png_loads(tmp_path):
    m = load_maps(specs_from_sources([f"svbrdf:{panel_png(tmp_path / 'a.png')}"], 0)[0])
    assert m.diffuse.shape == (16, 16, 3) and m.roughness.shape == (16, 16, 1)
    src = np.asarray(Image.open(tmp_path / "a.png"), dtype=np.float32) / 255
    np.testing.assert_array_equal(m.normal, src[:, 16:32])  # panel 2 is the normal
    np.testing.assert_array_equal(m.specular, src[:, 64:80])  # panel 5 is the specular


def test_map_folder_loads(tmp_path):
    m = load_maps(specs_from_sources([f"svbrdf:{map_folder(tmp_path / 'wood')}"], 0)[0])
    assert m.normal.shape == (16, 16, 3) and m.source_id == "wood"


def test_svbrdf_dir_lists_pngs_and_folders_in_order(tmp_path):
    panel_png(tmp_path / "b.png")
    panel_png(tmp_path / "a.png")
    map_folder(tmp_path / "c_folder")
    (tmp_path / "notes.txt").write_text("ignored")
    specs = specs_from_sources([f"svbrdf:{tmp_path}", "uniform:2", "procedural:1"], 0)
    assert [s.kind for s in specs] == ["svbrdf"] * 3 + ["uniform"] * 2 + ["procedural"]
    assert [s.source_id for s in specs[:3]] == ["a.png", "b.png", "c_folder"]
    again = specs_from_sources([f"svbrdf:{tmp_path}", "uniform:2", "procedural:1"], 0)
    assert again == specs
    assert specs_from_sources(["uniform:2"], 1) != specs_from_sources(["uniform:2"], 2)


def _error(tmp_path, spec_text):
    with pytest.raises(MaterialError) as info:
        for spec in specs_from_sources([spec_text], 0):
            load_maps(spec)
    message = str(info.value)
    assert "\n" not in message
    return message


def test_bad_input_wrong_panel_count(tmp_path):
    p = panel_png(tmp_path / "four.png", panels=4)
    msg = _error(tmp_path, f"svbrdf:{p}")
    assert "four.png" in msg and "5 square panels" in msg and "4.00 panels" in msg


def test_bad_input_not_an_image(tmp_path):
    p = tmp_path / "broken.png"
    p.write_bytes(b"this is not a png")
    msg = _error(tmp_path, f"svbrdf:{p}")
    assert "broken.png" in msg and "not a readable image" in msg


def test_bad_input_truncated_png(tmp_path):
    p = panel_png(tmp_path / "cut.png", size=64)
    p.write_bytes(p.read_bytes()[:200])
    assert "cut.png" in _error(tmp_path, f"svbrdf:{p}")


def test_bad_input_wrong_channel_count_panel(tmp_path):
    p = panel_png(tmp_path / "grey.png", channels=1)
    msg = _error(tmp_path, f"svbrdf:{p}")
    assert "grey.png" in msg and "channel" in msg


def test_bad_input_missing_map(tmp_path):
    folder = map_folder(tmp_path / "nometal", **{"wood_roughness.png": None})
    msg = _error(tmp_path, f"svbrdf:{folder}")
    assert "nometal" in msg and "no roughness map" in msg


def test_bad_input_normal_with_one_channel(tmp_path):
    grey = np.zeros((16, 16), np.uint8)
    folder = map_folder(tmp_path / "flat", **{"wood_normal.png": grey})
    msg = _error(tmp_path, f"svbrdf:{folder}")
    assert "wood_normal.png" in msg and "3 channels" in msg


def test_bad_input_coloured_roughness(tmp_path):
    colour = np.random.default_rng(0).integers(0, 256, (16, 16, 3), dtype=np.uint8)
    folder = map_folder(tmp_path / "orm", **{"wood_roughness.png": colour})
    assert "not greyscale" in _error(tmp_path, f"svbrdf:{folder}")


def test_bad_input_nan_values(tmp_path):
    arr = np.full((16, 16), 0.5, np.float32)
    arr[3, 4] = np.nan
    folder = map_folder(tmp_path / "nan", **{"wood_roughness.png": None})
    Image.fromarray(arr, mode="F").save(folder / "wood_roughness.tif")
    msg = _error(tmp_path, f"svbrdf:{folder}")
    assert "wood_roughness.tif" in msg and "NaN" in msg


def test_bad_input_ambiguous_map(tmp_path):
    folder = map_folder(tmp_path / "twice")
    save(folder / "other_albedo.png", np.zeros((16, 16, 3), np.uint8))
    assert "ambiguous base colour map: other_albedo.png, wood_basecolor.png" in _error(
        tmp_path, f"svbrdf:{folder}"
    )


def test_bad_input_empty_or_missing_dir(tmp_path):
    (tmp_path / "empty").mkdir()
    assert "no materials found" in _error(tmp_path, f"svbrdf:{tmp_path / 'empty'}")
    assert "no such directory" in _error(tmp_path, f"svbrdf:{tmp_path / 'nope'}")


@pytest.mark.parametrize(
    "text,needle",
    [
        ("uniform", "expected"),
        ("uniform:x", "integer"),
        ("uniform:0", ">= 1"),
        ("marble:3", "unknown kind"),
        ("procedural:", "expected"),
    ],
)
def test_bad_source_strings(text, needle):
    with pytest.raises(MaterialError, match=needle):
        parse_source(text)


def test_map_bytes_are_the_8_bit_values_blender_textures_hold():
    """A render worker sends its Blender process the maps as bytes: each value rounded half up
    to 8 bits in float32 arithmetic, as the textures' PNGs have always kept it."""
    m = procedural_maps(3, 32)
    edges = np.array([0.0, 0.5 / 255, 0.49 / 255, 0.5, 254.5 / 255, 1.0], np.float32)
    m.roughness[0, : len(edges), 0] = edges
    b = MapBytes.of(m)
    assert b.source_id == m.source_id and set(b.arrays) == set(MAP_CHANNELS)
    for name in MAP_CHANNELS:
        got, x = b.arrays[name], getattr(m, name)
        want = np.floor(x * np.float32(255) + np.float32(0.5)).astype(np.uint8)
        assert got.dtype == np.uint8 and got.shape == x.shape
        np.testing.assert_array_equal(got, want, err_msg=name)
    assert b.arrays["roughness"][0, : len(edges), 0].tolist() == [0, 1, 0, 128, 255, 255]


# ---- colour curves and threads ---------------------------------------------------------------


def test_srgb_curves_are_the_where_form_bit_for_bit_and_the_tables_their_levels():
    """The in-place curves give the values of the plain ``np.where`` form of IEC 61966-2-1 in
    float32 (every 16-bit level, random values, both thresholds' neighbours; negatives for the
    encode, which clamps them), and
    a table indexed by integer samples gives the curve of their floats."""
    from render_jobs.materials.maps import linear_to_srgb, srgb_table, srgb_to_linear

    def decode(x):
        return np.where(x <= 0.04045, x / 12.92, ((x + 0.055) / 1.055) ** 2.4).astype(np.float32)

    def encode(x):
        x = np.clip(x, 0.0, None)
        return np.where(x <= 0.0031308, x * 12.92, 1.055 * x ** (1 / 2.4) - 0.055).astype(
            np.float32
        )

    levels = np.arange(65536, dtype=np.float32) / np.float32(65535)
    near = [np.nextafter(np.float32(t), np.float32(d)) for t in (0.04045, 0.0031308)
            for d in (0, 1)]  # fmt: skip
    rng = np.random.default_rng(3)
    x = np.concatenate([levels, rng.random(100_000, dtype=np.float32) * 1.2, near,
                        np.float32([0.04045, 0.0031308, -0.5, 0.0, 1.0])])  # fmt: skip
    pos = x[x >= 0]  # a decode's input is a stored colour, never negative
    assert srgb_to_linear(pos).view(np.uint32).tolist() == decode(pos).view(np.uint32).tolist()
    assert linear_to_srgb(x).view(np.uint32).tolist() == encode(x).view(np.uint32).tolist()
    assert float(srgb_to_linear(np.float32(0.5))) == float(decode(np.float32(0.5)))
    samples = rng.integers(0, 256, (7, 5, 3), dtype=np.uint8)
    scaled = samples.astype(np.float32)
    scaled /= 255.0  # as images.Image.rows scales them
    np.testing.assert_array_equal(srgb_table(8)[samples], srgb_to_linear(scaled))
    np.testing.assert_array_equal(srgb_table(16), srgb_to_linear(levels))


def test_in_threads_keeps_order_and_raises_the_first_failing_items_error(monkeypatch):
    import os
    import threading
    import time
    from pathlib import Path

    from render_jobs.cpus import usable_cpus
    from render_jobs.materials import files
    from render_jobs.materials.files import in_threads

    seen = set()

    def square(x):
        seen.add(threading.get_ident())
        time.sleep(0.01 * (x % 3))  # finish out of order
        return x * x

    assert in_threads(square, list(range(12)), threads=4) == [x * x for x in range(12)]
    assert len(seen) > 1  # it did run on several threads
    started = []

    def fail(x):
        started.append(x)
        if x in (1, 2):
            time.sleep(0.05 if x == 1 else 0)  # item 2 fails first, item 1 is first in order
            raise MaterialError(f"item {x}")
        time.sleep(0.05)
        return x

    with pytest.raises(MaterialError, match="item 1"):
        in_threads(fail, list(range(40)), threads=4)
    assert len(started) < 40  # what had not started when it failed is dropped
    assert in_threads(square, [3], threads=4) == [9] and in_threads(square, []) == []
    monkeypatch.delenv("OMP_NUM_THREADS", raising=False)
    monkeypatch.delattr(os, "sched_getaffinity")  # as on macOS: every CPU counts
    assert usable_cpus(Path("/nonexistent/cpu.max")) == os.cpu_count()  # and no cgroup quota
    every = usable_cpus()  # this machine's cgroup quota, if it has one, still bounds it
    assert files._cpus() == every and in_threads(square, [1, 2]) == [1, 4]
    for value, cpus in (("1", 1), ("999", every), ("0", every), ("two", every)):
        monkeypatch.setenv("OMP_NUM_THREADS", value)  # Ray sets it to an actor's CPUs
        assert files._cpus() == cpus, value
    seen.clear()
    monkeypatch.setenv("OMP_NUM_THREADS", "1")
    assert in_threads(square, list(range(6))) == [x * x for x in range(6)]
    assert seen == {threading.get_ident()}  # one CPU: this thread alone


@pytest.mark.parametrize(
    "value,phrase",
    [(np.nan, "holds NaN or Inf"), (np.inf, "holds NaN or Inf"), (-np.inf, "holds NaN or Inf"),
     (1.5, "must lie in [0, 1], got [0.5, 1.5]"), (-0.25, "must lie in [0, 1], got [-0.25, 0.5]")],
)  # fmt: skip
def test_maps_with_a_bad_texel_are_refused_naming_the_map(value, phrase):
    from render_jobs.materials.maps import MaterialMaps

    maps = {name: np.full((8, 8, c), 0.5, np.float32) for name, c in MAP_CHANNELS.items()}
    maps["roughness"][5, 6] = value
    with pytest.raises(MaterialError) as info:
        MaterialMaps(**maps, source_id="m")
    assert str(info.value).startswith("m: roughness map") and phrase in str(info.value)


def test_map_bytes_of_any_source_are_its_maps_rounded(tmp_path):
    """``load_map_bytes`` (render workers, the viewer) gives ``MapBytes.of(load_maps)`` for
    every source kind; a file's are read straight to 8 bits."""
    from render_jobs.materials import load_map_bytes

    panel = panel_png(tmp_path / "p.png")
    folder = map_folder(tmp_path / "wood")
    sources = ["uniform:2", "procedural:2", f"svbrdf:{panel}", f"svbrdf:{folder}"]
    for spec in specs_from_sources(sources, 5, map_resolution=32):
        got, want = load_map_bytes(spec), MapBytes.of(load_maps(spec))
        assert got.source_id == want.source_id and list(got.arrays) == list(MAP_CHANNELS)
        for name, arr in want.arrays.items():
            np.testing.assert_array_equal(got.arrays[name], arr, err_msg=f"{spec} {name}")
