"""Screen-space maps without Blender: the store's screen UV layout (written by the farm) and
``trainer.rendering.mapping`` against Cycles' own AOV maps of the same materials, and
``trainer render --material`` from a checkpoint alone."""

from __future__ import annotations

import subprocess

import numpy as np
import pytest
import torch
from click.testing import CliRunner
from PIL import Image

from render_jobs.materials import load_maps
from render_jobs.materials.maps import MapBytes
from render_jobs.materials.procedural import procedural_maps
from render_jobs.screen_uv import ScreenUV, blackman_harris, filter_image, filter_taps
from render_jobs.specs import MaterialSpec
from storage.reader import Store
from storage.schema import MAP_CHANNELS
from tests.test_farm import BIN, farm
from tests.test_material_libraries import ambientcg, normal_map, write
from trainer.cli import main as trainer_main
from trainer.rendering.mapping import ScreenMapper, textures_from_bytes

#: the bound on every map of every material (uint8 maps, the store's own encoding)
MIN_PSNR_DB = 40.0


def psnr(a: np.ndarray, b: np.ndarray) -> float:
    mse = np.mean((a.astype(np.float64) - b.astype(np.float64)) ** 2)
    return float(10 * np.log10(255.0**2 / max(mse, 1e-12)))


def per_map(got: np.ndarray, want: np.ndarray) -> dict[str, float]:
    out, start = {}, 0
    for name, c in MAP_CHANNELS.items():
        out[name] = psnr(got[start : start + c], want[start : start + c])
        start += c
    return out


def textures_from_maps(maps):
    """A material's float maps as the 8-bit textures Blender loads."""
    return textures_from_bytes(MapBytes.of(maps))


# ---- the filter, alone --------------------------------------------------------------------


@pytest.mark.parametrize("s", [1, 2, 3, 4, 8])
def test_filter_taps_are_cycles_window_normalised_and_symmetric(s):
    taps = filter_taps(s)
    assert taps.shape == (3 * s,) and abs(taps.sum() - 1) < 1e-12
    np.testing.assert_allclose(taps, taps[::-1], atol=1e-12)
    # the centre pixel's share, from the closed-form integral of Cycles' window (width 1.5:
    # support ±1.5 px, cos(2πk(x/3 + 1/2)) terms)
    a = (0.35875, -0.48829, 0.14128, -0.01168)
    centre = a[0] + sum(
        a[k] * 3 / (2 * np.pi * k) * (np.sin(4 * np.pi * k / 3) - np.sin(2 * np.pi * k / 3))
        for k in (1, 2, 3)
    )
    assert abs(taps[s : 2 * s].sum() - centre / (3 * a[0])) < 1e-4
    assert blackman_harris(np.array([1.5, -1.5, 2.0])).max() < 1e-4


def test_filter_of_a_constant_is_the_constant_and_of_a_step_is_between():
    s = 4
    flat = np.full((1, 8 * s, 8 * s), 0.7, np.float32)
    out = filter_image(flat, s, filter_taps(s))
    np.testing.assert_allclose(out[0, 2:-2, 2:-2], 0.7, atol=1e-6)
    step = np.zeros((1, 8 * s, 8 * s), np.float32)
    step[:, :, 4 * s :] = 1.0  # a vertical edge on a pixel border
    row = filter_image(step, s, filter_taps(s))[0, 4]
    assert row[2] < 0.01 and row[5] > 0.99 and 0 < row[3] < 0.5 < row[4] < 1


def test_mapper_matches_the_numpy_reference_on_a_made_up_layout():
    rng = np.random.default_rng(0)
    r, s = 12, 3
    n = r * s
    hit = np.zeros((n, n), bool)
    hit[5:30, 4:33] = True
    uv = np.where(hit[..., None], rng.uniform(0, 1, (n, n, 2)), 0).astype(np.float32)
    layout = ScreenUV(uv, hit, r, s, 1.0, "made-up")
    tex = torch.rand(10, 8, 8)
    got = ScreenMapper(layout)(tex)[10].numpy()  # the mask channel: filtered hits
    want = np.round(np.clip(layout.coverage(), 0, 1) * 255)
    np.testing.assert_array_equal(got, want)
    roundtrip = ScreenUV.from_bytes(layout.to_bytes())
    np.testing.assert_array_equal(roundtrip.uv, uv)
    assert roundtrip.meta() == layout.meta()


@pytest.mark.parametrize("s", [2, 3, 4])
def test_the_pixel_filter_is_the_separable_filter_of_the_hit_sub_samples(s):
    """:class:`PixelFilter`'s two sparse products against the numpy reference filter of the
    whole sub-sample grid (misses as 0), on a layout whose hits reach the frame's edges and
    leave holes, for several channels at once."""
    from trainer.rendering.mapping import PixelFilter

    rng = np.random.default_rng(s)
    r = 11
    n = r * s
    hit = rng.uniform(size=(n, n)) < 0.6
    hit[0, :] = hit[:, -1] = True
    layout = ScreenUV(np.zeros((n, n, 2), np.float32), hit, r, s, 1.0, "made-up")
    index = torch.nonzero(torch.from_numpy(hit.reshape(-1))).squeeze(1)
    values = rng.uniform(size=(len(index), 4)).astype(np.float32)
    got = (PixelFilter.of(layout, index) @ torch.from_numpy(values)).numpy()
    grid = np.zeros((4, n * n))
    grid[:, index.numpy()] = values.T
    want = filter_image(grid.reshape(4, n, n), s, filter_taps(s)).reshape(4, r * r)
    np.testing.assert_allclose(got.T, want, atol=1e-6)


def tent_lookup(tex: np.ndarray, st: np.ndarray, tiling: float) -> np.ndarray:
    """Reference bilinear lookup, repeating: each texel's tent weight at each sample,
    summed over the texels around it, in float64. ``tex (C, H, W)`` (file row 0 is v = 1),
    ``st (n, 2)``: the samples' texture coordinates; ``(n, C)``."""
    c, h, w = tex.shape
    x = st[:, 0] * tiling * w - 0.5  # texel k's centre is at k + 0.5
    y = (1.0 - (st[:, 1] * tiling) % 1.0) * h - 0.5
    out = np.zeros((len(st), c))
    for dy in (-1, 0, 1, 2):
        ky = np.floor(y) + dy
        for dx in (-1, 0, 1, 2):
            kx = np.floor(x) + dx
            weight = np.maximum(0, 1 - abs(x - kx)) * np.maximum(0, 1 - abs(y - ky))
            texel = tex[:, ky.astype(int) % h, kx.astype(int) % w].T
            out += weight[:, None] * texel
    return out


@pytest.mark.parametrize("tiling", [1.0, 2.5, 0.3])
def test_lookups_are_bilinear_and_repeat_on_textures_of_any_size(tiling):
    """The mapper's lookups (before the colour decode) against a tent-weight reference, on
    odd sizes, with samples on texel centres, texel edges and the texture's own edges, for
    a batch of two textures; the colours are the sRGB decode of the same values."""
    from trainer.targets import srgb_decode

    rng = np.random.default_rng(1)
    r, s = 12, 3
    n = r * s
    hit = np.ones((n, n), bool)
    uv = rng.uniform(0, 1, (n, n, 2))
    uv[0, :6] = [[0, 0], [1 - 1e-9, 1 - 1e-9], [0.5 / 7, 0.5 / 5], [1 / 7, 0.2], [0, 0.5], [1, 1]]
    layout = ScreenUV(uv.astype(np.float32), hit, r, s, 2.0, "made-up")
    tex = torch.randint(0, 256, (2, 10, 5, 7), dtype=torch.uint8)
    mapper = ScreenMapper(layout)
    got = mapper.lookup(mapper.prepare(tex), tiling).double()  # (hits, 2, 10)
    st = mapper.st.numpy()
    for b in range(2):
        want = tent_lookup(tex[b].double().numpy() / 255.0, st, tiling)
        want[:, :6] = srgb_decode(torch.from_numpy(want[:, :6])).numpy()
        np.testing.assert_allclose(got[:, b].numpy(), want, atol=2e-6)


def _ties() -> np.ndarray:
    """float32 values in [0, 1] around every 8-bit rounding tie, with the ties themselves
    (values whose float32 ``v · 255`` ends in exactly .5), and a fine ramp."""
    k = np.arange(256, dtype=np.float64)
    centre = ((k + 0.5) / 255.0).astype(np.float32)
    near = [np.nextafter(centre, np.float32(s * np.inf)) for s in (-1, 1)]
    ramp = np.linspace(0.0, 1.0, 1 << 16, dtype=np.float32)
    return np.clip(np.concatenate([centre, *near, ramp]), 0.0, 1.0)


def test_mapper_rounds_textures_and_maps_as_blender_and_the_store_do_ties_up():
    from render_jobs.materials.maps import MapBytes, MaterialMaps
    from storage.schema import encode_maps
    from trainer.rendering.mapping import _levels

    v = _ties()
    ties = np.float32(v[:256] * np.float32(255.0)) % 1 == 0.5
    assert (ties & (np.arange(256) % 2 == 0)).any(), "no even tie: half-to-even would pass too"
    n = len(v)
    col = v.reshape(n, 1, 1)
    maps = MaterialMaps(np.repeat(col, 3, 2), np.repeat(col, 3, 2), col, np.repeat(col, 3, 2))
    want = MapBytes.of(maps).arrays
    got = textures_from_maps(maps).numpy()  # (10, n, 1): diffuse, specular, roughness, normal
    np.testing.assert_array_equal(got[6, :, 0], want["roughness"][:, 0, 0])
    np.testing.assert_array_equal(got[:3, :, 0].T, want["diffuse"][:, 0])
    plain = np.repeat(v[None, None], 3, 0)  # roughness, normal, mask as stored: no sRGB
    black = np.zeros((3, 1, n))
    stored = encode_maps(
        {"diffuse": black, "specular": black, "roughness": plain[:1], "normal": plain,
         "mask": plain[:1]}
    )  # fmt: skip
    levels = _levels(torch.from_numpy(v.copy())).to(torch.uint8).numpy()
    for channel in range(6, 11):
        np.testing.assert_array_equal(stored[channel, 0], levels)


def test_the_table_decode_is_the_srgb_curve_from_0_to_1_into_a_strided_output():
    from trainer.targets import srgb_decode

    hit = np.ones((6, 6), bool)
    mapper = ScreenMapper(ScreenUV(np.zeros((6, 6, 2), np.float32), hit, 3, 2, 1.0, "flat"))
    x = torch.cat([torch.linspace(0, 1, 100_001), torch.tensor([0.04045, 1.0 - 1e-7, 1.0])])
    out = torch.full((x.numel(), 2), -1.0)  # decoded into column 1: a stride of 2
    mapper._decode(x[None], out=out[:, 1][None])
    want = srgb_decode(x.double())
    assert (out[:, 1].double() - want).abs().max() < 1e-7 and (out[:, 0] == -1).all()


# ---- against Blender --------------------------------------------------------------------


@pytest.fixture(scope="module")
def aov_store(tmp_path_factory):
    """A real farm job at 64², 64 spp, one sun each: a uniform, a procedural and two file
    materials (a 5-panel PNG; an ambientCG-style metal-rough folder with JPEGs and a DirectX
    normal map)."""
    root = tmp_path_factory.mktemp("mapping")
    lib = root / "lib"
    panels = procedural_maps(11, 64)
    strip = np.concatenate(
        [panels.diffuse, panels.normal, panels.diffuse, np.repeat(panels.roughness, 3, 2),
         panels.specular], axis=1,
    )  # fmt: skip
    write(lib / "leather.png", strip)
    ambientcg(lib)
    out = root / "aov.zarr"
    r = farm("submit", "-m", "uniform:1", "-m", "procedural:1", "-m", f"svbrdf:{lib}",
             "--suns", "1", "--shard-size", "2", "--resolution", "64", "--samples", "64",
             "--workers", "1", "--no-ray-dashboard", "-o", out)  # fmt: skip
    assert r.returncode == 0, r.stderr[-3000:]
    return Store(str(out))


@pytest.mark.slow
def test_mapped_maps_match_the_stores_aov_maps(aov_store):
    layout = aov_store.screen_uv()
    assert layout is not None, "farm submit writes the store's screen UV layout"
    assert layout.resolution == 64 and layout.supersample == 4
    mapper = ScreenMapper(layout)
    kinds = set()
    for index, rec in sorted(aov_store.materials().items()):
        maps = load_maps(MaterialSpec.from_dict(rec["spec"]))
        got = mapper(textures_from_maps(maps)).numpy()
        scores = per_map(got, aov_store.packed_maps(index))
        print(rec["kind"], rec["source_id"], {k: round(v, 1) for k, v in scores.items()})
        assert min(scores.values()) >= MIN_PSNR_DB, (rec["source_id"], scores)
        kinds.add(rec["kind"])
    assert kinds == {"uniform", "procedural", "svbrdf"}


@pytest.mark.slow
def test_screen_uv_command_and_verify(aov_store, tmp_path):
    """farm screen-uv renders the same layout for a store made without one; shards verify
    and info see it; a corrupt one is reported."""
    import shutil

    copy = tmp_path / "copy.zarr"
    shutil.copytree(aov_store.url, copy)
    (copy / "screen_uv.npz").unlink()
    assert Store(str(copy)).screen_uv() is None
    r = subprocess.run([str(BIN / "farm"), "screen-uv", str(copy)], capture_output=True, text=True)
    assert r.returncode == 0, r.stderr
    again = Store(str(copy)).screen_uv()
    np.testing.assert_array_equal(again.hit, aov_store.screen_uv().hit)
    np.testing.assert_allclose(again.uv, aov_store.screen_uv().uv, atol=1e-6)
    info = subprocess.run([str(BIN / "shards"), "info", str(copy)], capture_output=True, text=True)
    assert "screen UV    4x4 sub-samples a pixel" in info.stdout
    raw = bytearray((copy / "screen_uv.npz").read_bytes())
    raw[len(raw) // 2] ^= 0xFF
    (copy / "screen_uv.npz").write_bytes(bytes(raw))
    v = subprocess.run([str(BIN / "shards"), "verify", str(copy)], capture_output=True, text=True)
    assert v.returncode == 1 and "screen_uv.npz" in v.stdout, v.stdout


@pytest.mark.slow
def test_trainer_render_any_material_from_the_checkpoint_alone(aov_store, tmp_path):
    """A checkpoint carries its store's layout: a new material renders from it alone, and
    the stored material's mapped maps render as its stored maps do."""
    run = tmp_path / "run"
    t = subprocess.run(
        [str(BIN / "trainer"), "train", "--store", aov_store.url, "--out", str(run), "--loss",
         "l1", "--epochs", "1", "--batch-size", "2", "--workers", "0", "--holdout-fraction", "0",
         "--width", "16"],
        capture_output=True, text=True,
    )  # fmt: skip
    assert t.returncode == 0, t.stderr[-2000:]
    lib = tmp_path / "lib"
    ambientcg(lib)
    grey = np.repeat(normal_map(16)[..., :1], 3, 2)
    write(lib / "rust.png", np.concatenate([normal_map(16)] * 3 + [grey, normal_map(16)], 1))

    def render(*args):  # in this process: each command's own torch import is most of its time
        return CliRunner().invoke(
            trainer_main, ["render", "--checkpoint", str(run), *map(str, args)]
        )

    for i, material in enumerate(
        [
            "uniform:diffuse=#b03a2e;specular=0.04;roughness=0.3",
            "procedural:seed=4",
            lib / "Bricks059_2K-JPG",
            lib / "rust.png",
        ]  # fmt: skip
    ):
        out = tmp_path / f"m{i}.png"
        r = render("--material", material, "--sun", "0.3,-0.5,0.8", "--turbidity", "4", "-o", out)
        assert r.exit_code == 0, r.output
        img = np.asarray(Image.open(out))
        assert img.shape == (64, 64, 3) and img.std() > 1
    # the first stored material: from its stored maps, and mapped from its source id
    source = aov_store.materials()[0]["source_id"]
    light = ["--sun", "0.3,-0.5,0.8", "--turbidity", "4"]
    stored = render("--store", aov_store.url, "--sample", 0, *light, "-o", tmp_path / "a.png")
    assert stored.exit_code == 0, stored.output
    assert render("--material", source, *light, "-o", tmp_path / "b.png").exit_code == 0
    a, b = (np.asarray(Image.open(tmp_path / f"{k}.png"), np.float64) for k in "ab")
    assert np.abs(a - b).mean() < 1.0, np.abs(a - b).mean()
    bad = render("--material", tmp_path / "nothing.png", "-o", tmp_path / "x.png")
    assert bad.exit_code == 1 and bad.stderr.strip().splitlines()[-1].startswith("Error: ")
    assert "nothing.png: no such file or folder" in bad.stderr
    assert not (tmp_path / "x.png").exists()
