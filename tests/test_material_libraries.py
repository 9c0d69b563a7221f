"""Material folders as libraries ship them (ambientCG, Poly Haven, Substance, spec-gloss sets),
in their formats (8/16-bit PNG, JPEG, TIFF, EXR), read, converted, dry-run and rendered."""

from __future__ import annotations

import json
import subprocess
from pathlib import Path

import cv2
import numpy as np
import pytest

from farm.materials import dry_run
from render_jobs.errors import MaterialError
from render_jobs.exr import write_image_exr
from render_jobs.materials import files
from render_jobs.materials.files import (
    metal_rough_to_spec_gloss,
    read_svbrdf,
    read_svbrdf_bytes,
)
from render_jobs.materials.library import role_of
from render_jobs.materials.maps import MapBytes, linear_to_srgb, srgb_to_linear
from storage.reader import Store
from tests.test_farm import BIN, TINY, assert_exactly_once, farm

S = 16  # texture size
RNG = np.random.default_rng(7)


def write(path: Path, rgb01: np.ndarray, bits: int = 8) -> Path:
    """An image in [0, 1] (``(H, W)`` or ``(H, W, 3)``) as an 8- or 16-bit file (or EXR)."""
    path.parent.mkdir(parents=True, exist_ok=True)
    if path.suffix == ".exr":
        arr = rgb01 if rgb01.ndim == 3 else rgb01[..., None]
        write_image_exr(path, np.ascontiguousarray(arr.transpose(2, 0, 1), np.float32))
        return path
    scale, dtype = (255, np.uint8) if bits == 8 else (65535, np.uint16)
    arr = np.round(np.clip(rgb01, 0, 1) * scale).astype(dtype)
    if arr.ndim == 3:
        arr = arr[..., ::-1]  # OpenCV writes BGR
    assert cv2.imwrite(str(path), arr)
    return path


def rand(*shape) -> np.ndarray:
    return RNG.uniform(0.05, 0.95, shape).astype(np.float32)


def normal_map(size: int = S) -> np.ndarray:
    n = RNG.normal(0, 0.2, (size, size, 3))
    n[..., 2] = 1
    n /= np.linalg.norm(n, axis=2, keepdims=True)
    return ((n + 1) / 2).astype(np.float32)


def ambientcg(root: Path) -> Path:
    d = root / "Bricks059_2K-JPG"
    write(d / "Bricks059_2K-JPG_Color.jpg", rand(S, S, 3))
    write(d / "Bricks059_2K-JPG_Roughness.jpg", rand(S, S))
    write(d / "Bricks059_2K-JPG_Metalness.jpg", np.zeros((S, S)))
    write(d / "Bricks059_2K-JPG_NormalDX.png", normal_map())
    write(d / "Bricks059_2K-JPG_AmbientOcclusion.jpg", rand(S, S))
    write(d / "Bricks059_2K-JPG_Displacement.jpg", rand(S, S))
    return d


def polyhaven(root: Path) -> Path:
    d = root / "metal_plate"
    write(d / "metal_plate_diff_1k.jpg", rand(S, S, 3))
    arm = np.stack([rand(S, S), rand(S, S), (RNG.uniform(size=(S, S)) > 0.5) * 1.0], -1)
    write(d / "metal_plate_arm_1k.png", arm)
    write(d / "metal_plate_nor_gl_1k.exr", normal_map())
    write(d / "metal_plate_disp_1k.png", rand(S, S), bits=16)
    return d


def substance(root: Path) -> Path:
    d = root / "rusty"
    write(d / "Rusty_BaseColor.png", rand(2 * S, 2 * S, 3), bits=16)  # the largest map
    write(d / "Rusty_Metallic.png", rand(S, S), bits=16)
    write(d / "Rusty_Roughness.tif", np.repeat(rand(S, S)[..., None], 3, 2), bits=16)  # grey RGB
    write(d / "Rusty_Normal.png", normal_map(), bits=16)
    write(d / "Rusty_Height.png", rand(S, S), bits=16)
    write(d / "Rusty_Mixed_AO.png", rand(S, S))
    write(d / "Rusty_Emissive.png", np.zeros((S, S, 3)))
    return d


def spec_gloss(root: Path) -> Path:
    d = root / "leather"
    write(d / "leather_diffuse.png", rand(S, S, 3))
    write(d / "leather_specular.png", rand(S, S, 3))
    write(d / "leather_glossiness.tif", rand(S, S), bits=16)
    write(d / "leather_normal.png", normal_map())
    return d


def both_workflows(root: Path) -> Path:
    """A folder with both sets: the explicit spec-gloss maps win."""
    d = root / "both"
    for name in ("diffuse", "specular", "basecolor"):
        write(d / f"tile_{name}.png", rand(S, S, 3))
    for name in ("roughness", "metallic", "height", "opacity"):
        write(d / f"tile_{name}.png", rand(S, S))
    write(d / "tile_normal.png", normal_map())
    return d


@pytest.fixture(scope="module")
def library(tmp_path_factory) -> Path:
    root = tmp_path_factory.mktemp("library")
    for make in (ambientcg, polyhaven, substance, spec_gloss, both_workflows):
        make(root)
    return root


@pytest.mark.parametrize(
    "name,role",
    [
        ("Bricks059_2K-JPG_Color.jpg", "basecolor"),
        ("Bricks059_2K-JPG_NormalDX.png", "normal_dx"),
        ("Bricks059_2K-JPG_NormalGL.png", "normal_gl"),
        ("Bricks059_2K-JPG_Metalness.jpg", "metallic"),
        ("metal_plate_diff_1k.jpg", "diffuse"),  # the last role word names the map
        ("metal_plate_metal_1k.jpg", "metallic"),
        ("metal_plate_nor_dx_1k.exr", "normal_dx"),
        ("metal_plate_arm_1k.png", "packed"),
        ("Rusty_BaseColor.png", "basecolor"),
        ("Rusty_Base_Color.png", "basecolor"),
        ("leather_glossiness.tif", "glossiness"),
        ("Rusty_Mixed_AO.png", None),
        ("Bricks059_2K-JPG_Displacement.jpg", None),
        ("photo.png", None),
    ],
)
def test_library_file_names(name, role):
    assert role_of(name) == role


def test_ambientcg_jpeg_set_with_a_directx_normal(library):
    maps, how = read_svbrdf(library / "Bricks059_2K-JPG")
    assert how.workflow == "metal-rough"
    assert how.files["normal"].startswith("Bricks059_2K-JPG_NormalDX.png")
    assert any("green flipped" in c for c in how.conversions)
    src = cv2.imread(str(library / "Bricks059_2K-JPG" / "Bricks059_2K-JPG_NormalDX.png"))
    np.testing.assert_allclose(maps.normal[..., 1], 1 - src[..., 1] / 255, atol=1e-6)
    ignored = {f for f, _ in how.ignored}
    assert ignored == {"Bricks059_2K-JPG_AmbientOcclusion.jpg", "Bricks059_2K-JPG_Displacement.jpg"}
    # metallic 0: diffuse is the base colour, specular the dielectric 0.04
    np.testing.assert_allclose(srgb_to_linear(maps.specular), 0.04, atol=1e-5)


def test_polyhaven_packed_arm_and_exr_normal(library):
    d = library / "metal_plate"
    maps, how = read_svbrdf(d)
    arm = cv2.imread(str(d / "metal_plate_arm_1k.png"))[..., ::-1] / 255.0
    np.testing.assert_allclose(maps.roughness[..., 0], arm[..., 1], atol=1e-6)
    base = srgb_to_linear(cv2.imread(str(d / "metal_plate_diff_1k.jpg"))[..., ::-1] / 255.0)
    want_diffuse, want_spec = metal_rough_to_spec_gloss(base, arm[..., 2:3])
    np.testing.assert_allclose(srgb_to_linear(maps.diffuse), want_diffuse, atol=2e-5)
    np.testing.assert_allclose(srgb_to_linear(maps.specular), want_spec, atol=2e-5)
    assert how.files["normal"].endswith("(16x16 float, 3 channel(s))")
    assert [f for f, _ in how.ignored] == ["metal_plate_disp_1k.png"]


def test_substance_16_bit_set_of_mixed_sizes(library):
    d = library / "rusty"
    maps, how = read_svbrdf(d)
    assert maps.size == (2 * S, 2 * S)  # resampled to the largest map
    assert sum("resampled from 16x16 to 32x32" in c for c in how.conversions) == 3
    base16 = cv2.imread(str(d / "Rusty_BaseColor.png"), cv2.IMREAD_UNCHANGED)
    assert base16.dtype == np.uint16  # and read at 16 bits, not 8:
    metal = cv2.resize(
        cv2.imread(str(d / "Rusty_Metallic.png"), cv2.IMREAD_UNCHANGED) / 65535.0,
        (2 * S, 2 * S),
        interpolation=cv2.INTER_LINEAR,
    )[..., None]
    want, _ = metal_rough_to_spec_gloss(srgb_to_linear(base16[..., ::-1] / 65535.0), metal)
    np.testing.assert_allclose(srgb_to_linear(maps.diffuse), want, atol=2e-5)
    assert {f for f, _ in how.ignored} == {"Rusty_Height.png", "Rusty_Mixed_AO.png",
                                           "Rusty_Emissive.png"}  # fmt: skip


def test_a_smaller_8_bit_map_is_resampled_in_8_bits(tmp_path):
    """A map smaller than the set's largest is resampled as it is stored (no float copy):
    the roughness is OpenCV's bilinear 8-bit resize of the file, exactly."""
    d = tmp_path / "mixed"
    write(d / "mixed_Color.png", rand(2 * S, 2 * S, 3))
    rough = write(d / "mixed_Roughness.png", rand(S, S))
    write(d / "mixed_NormalGL.png", normal_map(2 * S))
    maps, how = read_svbrdf(d)
    assert maps.size == (2 * S, 2 * S)
    assert "mixed_Roughness.png resampled from 16x16 to 32x32" in how.conversions
    want = cv2.resize(cv2.imread(str(rough), cv2.IMREAD_UNCHANGED), (2 * S, 2 * S),
                      interpolation=cv2.INTER_LINEAR)  # fmt: skip
    assert want.dtype == np.uint8
    np.testing.assert_array_equal(maps.roughness[..., 0], want / np.float32(255.0))


def test_glossiness_is_inverted(library):
    d = library / "leather"
    maps, how = read_svbrdf(d)
    gloss = cv2.imread(str(d / "leather_glossiness.tif"), cv2.IMREAD_UNCHANGED) / 65535.0
    np.testing.assert_allclose(maps.roughness[..., 0], 1 - gloss, atol=1e-6)
    assert how.workflow == "spec-gloss" and "roughness = 1 - glossiness" in how.conversions


def test_both_workflows_in_one_folder_take_the_explicit_spec_gloss_maps(library):
    _, how = read_svbrdf(library / "both")
    assert how.workflow == "spec-gloss"
    assert how.files["diffuse"].startswith("tile_diffuse.png")
    why = dict(how.ignored)
    assert set(why) == {"tile_basecolor.png", "tile_metallic.png", "tile_height.png",
                        "tile_opacity.png"}  # fmt: skip
    assert "not used by the spec-gloss rules" in why["tile_metallic.png"]


def test_a_metal_rough_uniform_material_equals_its_spec_gloss_equivalent(tmp_path):
    base_srgb, metallic, rough = np.array([0.8, 0.5, 0.2]), 0.3, 0.4
    mr = tmp_path / "mr"
    write(mr / "m_basecolor.png", np.broadcast_to(base_srgb, (S, S, 3)), bits=16)
    write(mr / "m_metallic.png", np.full((S, S), metallic), bits=16)
    write(mr / "m_roughness.png", np.full((S, S), rough), bits=16)
    # the same material, converted by hand (glTF 2.0): linear base, F0 0.04 for dielectrics
    base = srgb_to_linear(base_srgb.astype(np.float32))
    diffuse = linear_to_srgb(base * (1 - metallic))
    specular = linear_to_srgb(0.04 * (1 - metallic) + base * metallic)
    sg = tmp_path / "sg"
    write(sg / "m_diffuse.png", np.broadcast_to(diffuse, (S, S, 3)), bits=16)
    write(sg / "m_specular.png", np.broadcast_to(specular, (S, S, 3)), bits=16)
    write(sg / "m_roughness.png", np.full((S, S), rough), bits=16)
    a, how_a = read_svbrdf(mr)
    b, how_b = read_svbrdf(sg)
    assert (how_a.workflow, how_b.workflow) == ("metal-rough", "spec-gloss")
    for name in ("diffuse", "specular", "roughness", "normal"):
        np.testing.assert_allclose(getattr(a, name), getattr(b, name), atol=1e-4, err_msg=name)


def test_reading_in_bands_of_rows_gives_the_same_maps(library, tmp_path, monkeypatch):
    """Files are converted a few rows at a time: the maps equal those of one whole pass (a
    float material, polyhaven's EXR normal, is always one pass), and a map that is coloured
    only in its last rows is still caught."""
    panels = rand(S, 5 * S, 3)
    panels[:, 3 * S : 4 * S] = panels[:, 3 * S : 4 * S, :1]  # a grey roughness panel
    five = write(tmp_path / "five.png", panels)
    whole = {p.name: read_svbrdf(p) for p in [*sorted(library.iterdir()), five]}
    monkeypatch.setattr(files, "BAND_PIXELS", 5 * S)  # 5 rows of a 16-wide map, 1 of a panel
    ints = [files.images.read(library / "leather" / "leather_diffuse.png")]
    assert files.band_rows((S, S), ints) == 5 and files.band_rows((S, 5 * S), ints) == 1
    exr = files.images.read(library / "metal_plate" / "metal_plate_nor_gl_1k.exr")
    assert files.band_rows((S, S), [*ints, exr]) == S  # a float file: one pass
    for name, (maps, how) in whole.items():
        path = library / name if name != "five.png" else five
        banded, how_banded = read_svbrdf(path)
        assert how_banded == how, name
        for m in ("diffuse", "specular", "roughness", "normal"):
            np.testing.assert_array_equal(getattr(banded, m), getattr(maps, m), err_msg=name)
        levels, how_levels = read_svbrdf_bytes(path)  # 8 bits a band at a time: the same
        assert how_levels == how and levels.source_id == maps.source_id, name
        for m, want in MapBytes.of(maps).arrays.items():
            assert levels.arrays[m].flags.c_contiguous, name
            np.testing.assert_array_equal(levels.arrays[m], want, err_msg=f"{name} {m}")
    d = spec_gloss(tmp_path / "late")
    gloss = np.repeat(rand(S, S)[..., None], 3, 2)
    gloss[-1, -1] = [0.1, 0.9, 0.5]
    write(d / "leather_glossiness.tif", gloss, bits=16)
    for read in (read_svbrdf, read_svbrdf_bytes):
        with pytest.raises(MaterialError, match="leather_glossiness.tif: glossiness map is not g"):
            read(d)


def broken(root: Path) -> dict[str, tuple[Path, str]]:
    """Broken materials: folder -> (the culprit named in the error, a phrase of it)."""
    out = {}
    d = spec_gloss(root / "truncated")
    exr = write(d / "leather_roughness.exr", rand(S, S))  # beside glossiness: roughness wins
    exr.write_bytes(exr.read_bytes()[:120])
    out["truncated"] = (exr, "not a readable EXR")
    d = spec_gloss(root / "nan")
    bad = rand(S, S)
    bad[2, 3] = np.nan
    out["nan"] = (write(d / "leather_roughness.exr", bad), "NaN")
    d = polyhaven(root / "colour_metal")
    (d / "metal_plate_arm_1k.png").unlink()
    write(d / "metal_plate_rough_1k.png", rand(S, S))
    out["colour_metal"] = (write(d / "metal_plate_metal_1k.png", rand(S, S, 3)), "not greyscale")
    d = ambientcg(root / "two_base")
    write(d / "Bricks059_2K-JPG_Albedo.png", rand(S, S, 3))
    out["two_base"] = (d, "ambiguous base colour map")
    return out


def test_broken_materials_give_one_line_errors_and_the_farm_writes_nothing(tmp_path):
    cases = broken(tmp_path / "broken")
    for folder, (culprit, phrase) in cases.items():
        root = next(p for p in (tmp_path / "broken" / folder).iterdir() if p.is_dir())
        for read in (read_svbrdf, read_svbrdf_bytes):
            with pytest.raises(MaterialError) as info:
                read(root)
            msg = str(info.value)
            assert "\n" not in msg and str(culprit) in msg and phrase in msg, msg
    run = dry_run([f"svbrdf:{tmp_path / 'broken' / name}" for name in cases])
    assert run.failed == len(cases) and all(e.error for e in run.entries)
    out = tmp_path / "never.zarr"
    r = farm("submit", "-m", f"svbrdf:{tmp_path / 'broken' / 'nan'}", *TINY, "-o", out)
    assert r.returncode == 1 and "NaN" in r.stderr.strip().splitlines()[-1]
    assert "Traceback" not in r.stderr and not out.exists()


def test_farm_materials_dry_run(library, tmp_path):
    r = subprocess.run(
        [str(BIN / "farm"), "materials", f"svbrdf:{library}", "uniform:2", "--json"],
        capture_output=True,
        text=True,
    )
    assert r.returncode == 0, r.stderr
    got = json.loads(r.stdout)
    by_id = {m["source_id"]: m for m in got["materials"]}
    assert got["usable"] == 7 and got["failed"] == 0
    assert by_id["metal_plate"]["workflow"] == "metal-rough"
    assert set(by_id["metal_plate"]["files"]) == {"basecolor", "packed", "normal"}
    assert {i["file"] for i in by_id["rusty"]["ignored"]} >= {"Rusty_Height.png"}
    text = subprocess.run(
        [str(BIN / "farm"), "materials", f"svbrdf:{library}"], capture_output=True, text=True
    ).stdout
    assert "ok      #1 both  (spec-gloss)" in text
    assert "5 usable, 0 failed" in text
    bad = tmp_path / "five_panels"
    write(bad / "0001.png", rand(S, 5 * S, 3))
    r = farm("preview", "-m", bad, "-o", tmp_path / "p")
    assert r.returncode == 1 and "a folder of materials (5-panel PNGs)" in r.stderr


@pytest.mark.slow
def test_every_library_layout_renders_in_a_farm_job(library, tmp_path):
    out = tmp_path / "lib.zarr"
    r = farm("submit", "-m", f"svbrdf:{library}", *TINY, "--workers", "2", "-o", out)
    assert r.returncode == 0, r.stderr[-2000:]
    assert_exactly_once(out, 5)
    store = Store(str(out))
    ids = [m["source_id"] for s in store.commits().values() for m in s["materials"]]
    assert sorted(ids) == ["Bricks059_2K-JPG", "both", "leather", "metal_plate", "rusty"]
    renders = store.group["renders"][:].astype(np.float32)
    assert np.isfinite(renders).all() and renders.max() > 0


def test_a_float_base_colour_is_taken_as_linear_and_8_bit_levels_decode_by_table(tmp_path):
    """An EXR base colour is linear: with no metal, the diffuse map is its sRGB encoding,
    exactly; an 8-bit base colour's decode is the curve of its levels."""
    base = rand(S, S, 3)
    d = tmp_path / "exr"
    write(d / "m_BaseColor.exr", base)
    write(d / "m_Roughness.png", rand(S, S))
    maps, how = read_svbrdf(d)
    assert how.workflow == "metal-rough"
    np.testing.assert_array_equal(maps.diffuse, linear_to_srgb(base))
    np.testing.assert_array_equal(maps.specular, linear_to_srgb(np.full_like(base, 0.04)))
    d = tmp_path / "png"
    write(d / "m_BaseColor.png", rand(S, S, 3))
    write(d / "m_Roughness.png", rand(S, S))
    metal = write(d / "m_Metallic.png", rand(S, S))
    maps, _ = read_svbrdf(d)
    levels = cv2.imread(str(d / "m_BaseColor.png"))[..., ::-1].astype(np.float32) / np.float32(255)
    m = cv2.imread(str(metal), cv2.IMREAD_UNCHANGED)[..., None].astype(np.float32) / np.float32(255)
    want, _ = metal_rough_to_spec_gloss(srgb_to_linear(levels), m)
    np.testing.assert_array_equal(maps.diffuse, linear_to_srgb(want))
