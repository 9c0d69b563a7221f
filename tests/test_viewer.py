"""``trainer viewer``: edits, light and uploads as plain code; the server's security and its
answers to bad uploads; and (slow) the page in headless Chromium on a checkpoint trained on a
tiny real store: drag the sun, change roughness, upload a good and a broken material, save."""

from __future__ import annotations

import hashlib
import io
import json
import os
import subprocess
import sys
import time
import urllib.error
import urllib.request
import uuid
from pathlib import Path

import numpy as np
import pytest
import torch
from PIL import Image

from render_jobs.errors import MaterialError
from render_jobs.materials.procedural import procedural_maps
from tests.servers import ServerProcess
from tests.test_dashboard import ARTIFACTS, chromium
from tests.test_farm import BIN
from tests.test_mapping import textures_from_maps
from trainer.rendering.viewer.engine import Light
from trainer.rendering.viewer.materials import MAX_PIXELS, Edits, Library, direction, sun_angles

# ---- plain parts ----------------------------------------------------------------------------


def test_edits_from_the_query_check_every_value():
    e = Edits.from_query({"roughness_scale": "0.5", "diffuse_tint": "#ff8000", "tiling": "2"})
    assert e.roughness_scale == 0.5 and e.tiling == 2.0
    assert e.diffuse_tint == (1.0, 128 / 255, 0.0)
    assert Edits.from_query({}).identity
    for query, culprit in [
        ({"roughness_scale": "x"}, "roughness_scale='x' is not a number"),
        ({"tiling": "100"}, "tiling=100 is outside"),
        ({"diffuse_tint": "red"}, "diffuse_tint='red' is not a #rrggbb colour"),
    ]:
        with pytest.raises(ValueError, match=culprit):
            Edits.from_query(query)


def test_edits_change_what_they_name_and_nothing_else():
    samples = torch.rand(500, 1, 10)  # sub-samples as the mapper hands them over
    samples[..., 9] = 0.55 + 0.45 * samples[..., 9]  # normals point out of the surface

    def edited(**kw):
        kept = samples.clone()
        out = Edits(**kw).adjust(samples)
        assert torch.equal(samples, kept)  # a new tensor: the looked-up values are kept
        return out

    assert torch.equal(edited(), samples) and torch.equal(edited(tiling=3.0), samples)
    rough = edited(roughness_scale=0.5)
    torch.testing.assert_close(rough[..., 6], samples[..., 6] * 0.5)
    others = [0, 1, 2, 3, 4, 5, 7, 8, 9]
    assert torch.equal(rough[..., others], samples[..., others])
    flat = edited(normal_strength=0.0)
    torch.testing.assert_close(flat[..., 7:10], torch.tensor([0.5, 0.5, 1.0]).expand(500, 1, 3))
    red = edited(diffuse_tint=(1.0, 0.0, 0.0), specular_scale=0.5)
    assert red[..., 1:3].max() == 0 and torch.equal(red[..., 0], samples[..., 0])
    torch.testing.assert_close(red[..., 3:6], samples[..., 3:6] * 0.5)


def made_up_mapper():
    """A :class:`ScreenMapper` on a made-up 16² layout (3² sub-samples, random UVs)."""
    from render_jobs.screen_uv import ScreenUV
    from trainer.rendering.mapping import ScreenMapper

    rng = np.random.default_rng(1)
    n = 16 * 3
    hit = np.zeros((n, n), bool)
    hit[6:40, 6:40] = True
    uv = np.where(hit[..., None], rng.uniform(0, 1, (n, n, 2)), 0).astype(np.float32)
    return ScreenMapper(ScreenUV(uv, hit, 16, 3, 1.0, "made-up"))


def test_an_edit_maps_as_the_edited_material(tmp_path):
    """Mapping with a roughness edit equals mapping the texture with that roughness, within
    the 8-bit rounding of the texture Blender would load."""
    mapper = made_up_mapper()
    tex = textures_from_maps(procedural_maps(2, 32))
    halved = tex.float() / 255.0
    halved[6] *= 0.5
    a = mapper(tex, adjust=Edits(roughness_scale=0.5).adjust).int()
    b = mapper(halved).int()
    assert (a[6] - b[6]).abs().max() <= 1 and torch.equal(a[[0, 1, 2, 10]], b[[0, 1, 2, 10]])


def test_recent_keeps_the_most_recently_used():
    from trainer.rendering.viewer.recent import Recent

    r = Recent(2)
    r.put("a", 1)
    r.put("b", 2)
    assert r.get("a") == 1  # now the most recent
    r.put("c", 3)
    assert (r.get("a"), r.get("b"), r.get("c"), len(r)) == (1, None, 3, 2)
    with pytest.raises(ValueError, match="size must be at least 1"):
        Recent(0)


def test_recent_with_a_byte_budget_drops_the_oldest_bytes_and_keeps_the_newest():
    from trainer.rendering.viewer.recent import Recent

    r = Recent(8, max_bytes=100)
    r.put("a", np.zeros(40, np.uint8))
    r.put("b", np.zeros(40, np.uint8))
    assert r.bytes == 80 and len(r) == 2
    r.get("a")  # now the most recent
    r.put("c", np.zeros(40, np.uint8))  # 120 bytes: "b", the least recent, goes
    assert r.get("b") is None and r.bytes == 80 and r.get("a") is not None
    r.put("a", np.zeros(10, np.uint8))  # a new value for a key counts once
    assert r.bytes == 50 and len(r) == 2
    r.put("big", torch.zeros(50, dtype=torch.float32))  # 200 bytes alone: kept, the rest go
    assert len(r) == 1 and r.bytes == 200 and r.get("big") is not None
    assert r.pop("big").nbytes == 200 and r.bytes == 0 and r.pop("big") is None
    with pytest.raises(ValueError, match="max_bytes must be at least 1"):
        Recent(2, max_bytes=0)


def test_textures_are_the_8_bit_values_and_prepare_the_same_from_bytes_or_floats():
    """The library keeps a material's textures as bytes (a quarter of floats); the mapper
    prepares the same rows of texels from them as from the float maps, so it maps the
    same."""
    maps = procedural_maps(5, 24)
    tex = textures_from_maps(maps)
    floats = np.concatenate([maps.diffuse, maps.specular, maps.roughness, maps.normal], axis=2)
    want = np.round(np.clip(floats, 0, 1) * 255).astype(np.uint8).transpose(2, 0, 1)
    assert tex.dtype == torch.uint8 and np.array_equal(tex.numpy(), want)
    mapper = made_up_mapper()
    from_floats = mapper.prepare(torch.from_numpy(floats.transpose(2, 0, 1).copy()))
    from_bytes = mapper.prepare(tex)
    assert torch.equal(from_bytes, from_floats) and from_bytes.dtype == torch.uint8
    rows = torch.from_numpy(want).permute(1, 2, 0)  # (H, W, 10), then the repeat wrap
    assert torch.equal(from_bytes, torch.cat([rows, rows[:1]])[:, [*range(24), 0]])
    assert torch.equal(tex, torch.from_numpy(want))  # prepare left its input as it was


def test_lookups_on_any_thread_count_are_the_same_numbers_and_finish_keeps_them():
    mapper = made_up_mapper()
    prepared = mapper.prepare(textures_from_maps(procedural_maps(4, 40)))
    threads = torch.get_num_threads()
    try:
        torch.set_num_threads(1)
        one = mapper.lookup(prepared, 1.7)
        torch.set_num_threads(3)  # the hits do not divide evenly
        three = mapper.lookup(prepared, 1.7)
    finally:
        torch.set_num_threads(threads)
    assert one.shape == (mapper.hits, 1, 10) and torch.equal(one, three)
    kept = three.clone()
    mapper.finish(three, Edits(roughness_scale=0.2, diffuse_tint=(1.0, 0.5, 0.0)).adjust)
    assert torch.equal(three, kept)


def test_pictures_are_quantized_where_the_network_ran_to_the_bytes_of_to_uint8():
    """``trainer.rendering.viewer.engine.to_uint8_tensor``: the bytes
    ``render_jobs.tonemap.to_uint8``
    makes of the same image, the halfway values of the 8-bit rounding and values outside
    [0, 1] among them; and a frame's picture is the network's image so quantized."""
    from render_jobs.tonemap import to_uint8
    from trainer.model import ModelConfig, NeuralRenderer
    from trainer.rendering.infer import Renderer
    from trainer.rendering.viewer.engine import Engine, to_uint8_tensor
    from trainer.targets import Tonemap

    gen = torch.Generator().manual_seed(0)
    image = torch.rand(3, 40, 56, generator=gen) * 1.2 - 0.1
    halfway = (torch.arange(256) + 0.5) / 255.0
    image.view(-1)[: halfway.numel()] = halfway
    image.view(-1)[256 : 256 + 255] = torch.nextafter(halfway[:-1], torch.zeros(()))
    want = to_uint8(image.numpy())
    got = to_uint8_tensor(image)
    assert got.shape == (40, 56, 3) and got.is_contiguous()
    assert np.array_equal(got.numpy(), want)

    torch.manual_seed(0)
    renderer = Renderer(NeuralRenderer(ModelConfig(16, width=4)), Tonemap(), torch.device("cpu"))
    engine = Engine(renderer, None, Library([], [], Path("unused")), "-")
    packed = torch.randint(0, 256, (1, 11, 16, 16), dtype=torch.uint8)
    light = np.array([0.3, 0.2, 0.9, 0.3], np.float32)
    assert np.array_equal(engine.picture(packed, light), to_uint8(engine.network(packed, light)))


def test_the_engine_reuses_lookups_for_value_edits_and_maps_as_a_fresh_engine(tmp_path):
    """An edit of values after another maps from the kept lookups, to the same maps a fresh
    engine makes; a new tiling looks the textures up again."""
    from trainer.model import ModelConfig, NeuralRenderer
    from trainer.rendering.infer import Renderer
    from trainer.rendering.viewer.engine import Engine
    from trainer.targets import Tonemap

    lib = tmp_path / "lib"
    lib.mkdir()
    (lib / "m.png").write_bytes(panel(32))
    renderer = Renderer(NeuralRenderer(ModelConfig(16, width=4)), Tonemap(), torch.device("cpu"))

    def engine():
        e = Engine(renderer, made_up_mapper(), Library([], [str(lib)], tmp_path / "up"), "-")
        lookups = []
        lookup = e.mapper.lookup
        e.mapper.lookup = lambda *a: lookups.append(a[1:]) or lookup(*a)
        return e, lookups

    first, lookups = engine()
    mid = next(iter(first.library.entries))
    edited = Edits(roughness_scale=0.3, specular_scale=2.0)
    first.maps(mid, Edits(roughness_scale=0.7))
    maps, _, cached = first.maps(mid, edited)
    assert not cached and lookups == [(1.0,)]
    fresh, _ = engine()
    assert torch.equal(maps, fresh.maps(mid, edited)[0])
    assert first.maps(mid, edited)[2]  # the same edits again: the mapped maps are kept
    tiled, _, _ = first.maps(mid, Edits(roughness_scale=0.3, specular_scale=2.0, tiling=2.0))
    assert lookups == [(1.0,), (2.0,)] and not torch.equal(tiled, maps)
    assert len(first.library._textures) == 0  # held once: as the engine's prepared textures


def test_an_edit_of_one_map_maps_that_map_alone_to_the_bytes_of_mapping_all(tmp_path):
    """Edits one map at a time (as sliders move) map only that map's channels again, from
    the last maps of the material; each result is, byte for byte, what a fresh engine maps
    with every channel; an edit of two maps at once maps them all."""
    from trainer.model import ModelConfig, NeuralRenderer
    from trainer.rendering.infer import Renderer
    from trainer.rendering.mapping import CHANNEL_GROUPS
    from trainer.rendering.viewer.engine import Engine
    from trainer.targets import Tonemap

    lib = tmp_path / "lib"
    lib.mkdir()
    (lib / "m.png").write_bytes(panel(32))
    renderer = Renderer(NeuralRenderer(ModelConfig(16, width=4)), Tonemap(), torch.device("cpu"))

    def engine():
        return Engine(renderer, made_up_mapper(), Library([], [str(lib)], tmp_path / "up"), "-")

    sliding = engine()
    calls = []
    finish, finish_channels = sliding.mapper.finish, sliding.mapper.finish_channels
    sliding.mapper.finish = lambda *a: calls.append("all") or finish(*a)
    sliding.mapper.finish_channels = lambda *a: calls.append(a[1]) or finish_channels(*a)
    mid = next(iter(sliding.library.entries))
    steps = [
        (Edits(roughness_scale=0.5), ["all"]),  # nothing mapped before: every map
        (Edits(roughness_scale=2.5), [CHANNEL_GROUPS["roughness"]]),  # clamped above 1
        (Edits(roughness_scale=2.5, diffuse_tint=(1.0, 0.2, 0.7), diffuse_scale=3.0),
         [CHANNEL_GROUPS["diffuse"]]),
        (Edits(roughness_scale=2.5, diffuse_tint=(1.0, 0.2, 0.7), diffuse_scale=3.0,
               specular_scale=0.4), [CHANNEL_GROUPS["specular"]]),
        (Edits(roughness_scale=2.5, diffuse_tint=(1.0, 0.2, 0.7), diffuse_scale=3.0,
               specular_scale=0.4, normal_strength=0.0), [CHANNEL_GROUPS["normal"]]),
        (Edits(roughness_scale=2.5, specular_scale=0.4, normal_strength=0.0),
         [CHANNEL_GROUPS["diffuse"]]),  # back to its own values
        (Edits(roughness_scale=1.5, normal_strength=3.0), ["all"]),  # three maps at once
        (Edits(roughness_scale=1.5), [CHANNEL_GROUPS["normal"]]),
    ]  # fmt: skip
    for edits, mapped in steps:
        calls.clear()
        got, _, cached = sliding.maps(mid, edits)
        assert not cached and calls == mapped, edits
        assert torch.equal(got, engine().maps(mid, edits)[0]), edits


def test_an_uploads_textures_are_read_once_and_then_held_by_the_engine_alone(tmp_path):
    from trainer.model import ModelConfig, NeuralRenderer
    from trainer.rendering.infer import Renderer
    from trainer.rendering.viewer.engine import Engine
    from trainer.targets import Tonemap

    renderer = Renderer(NeuralRenderer(ModelConfig(16, width=4)), Tonemap(), torch.device("cpu"))
    library = Library([], [], tmp_path / "up")
    engine = Engine(renderer, made_up_mapper(), library, "-")
    e = library.add_upload([("m.png", panel(32))])
    assert library._textures.get(e.id) is not None  # read to check it: kept for its frame
    (library.upload_dir / e.id / "m.png").unlink()  # a second read would fail
    engine.maps(e.id, Edits())
    assert len(library._textures) == 0 and library._textures.bytes == 0
    assert engine._prepared.get(e.id) is not None


def test_light_angles_round_trip_and_bad_suns_are_refused():
    d = direction(123.0, 37.0)
    back = sun_angles(d, 4.0)
    assert abs(back["azimuth"] - 123) < 1e-6 and abs(back["elevation"] - 37) < 1e-6
    assert Light.from_query({"az": "10", "el": "45", "t": "2"}).turbidity == 2.0
    for query in ({"el": "-5"}, {"t": "11"}, {"az": "east"}):
        with pytest.raises(ValueError):
            Light.from_query(query)


def png_bytes(arr: np.ndarray) -> bytes:
    buf = io.BytesIO()
    Image.fromarray(arr).save(buf, format="PNG")
    return buf.getvalue()


def panel(size: int = 16, panels: int = 5) -> bytes:
    rng = np.random.default_rng(3)
    arr = rng.integers(0, 256, (size, size * panels, 3), dtype=np.uint8)
    arr[:, 3 * size : 4 * size] = arr[:, 3 * size : 4 * size, :1]  # a grey roughness panel
    return png_bytes(arr)


def bomb() -> bytes:
    """A small PNG whose header declares 40,000 x 40,000 pixels (it would decode to 4.8 GB)."""
    img = png_bytes(np.zeros((1, 1, 3), np.uint8))
    ihdr = img.index(b"IHDR")
    body = img[ihdr : ihdr + 4] + (40000).to_bytes(4, "big") * 2 + img[ihdr + 12 : ihdr + 17]
    import zlib

    crc = zlib.crc32(body).to_bytes(4, "big")
    return img[: ihdr + 4] + body[4:] + crc + img[ihdr + 21 :]


BAD_UPLOADS = [
    ([("notes.png", b"this is not an image")], "notes.png"),
    ([("cut.png", panel()[:300])], "cut.png"),
    ([("four.png", panel(panels=4))], "four.png"),
    (
        [("bomb.png", bomb())],
        f"bomb.png: the image is over the viewer's limit of {MAX_PIXELS:,}",
    ),
]


@pytest.mark.parametrize(
    "files,culprit", BAD_UPLOADS, ids=["not-image", "truncated", "panels", "bomb"]
)
def test_bad_uploads_get_one_line_naming_the_file_and_leave_nothing(tmp_path, files, culprit):
    lib = Library([], [], tmp_path / "uploads")
    with pytest.raises(MaterialError) as info:
        lib.add_upload(files)
    message = str(info.value)
    assert "\n" not in message and culprit in message, message
    assert str(tmp_path) not in message  # the page sees the file's name, not the server's paths
    assert not any((tmp_path / "uploads").rglob("*.png"))
    good = lib.add_upload([("good.png", panel())])
    assert good.id in lib.entries and lib.textures(good.id).shape == (10, 16, 16)


def test_an_upload_the_server_received_into_a_file_is_moved_in_and_the_limit_holds(tmp_path):
    lib = Library([], [], tmp_path / "uploads", max_upload_bytes=1 << 20)
    incoming = tmp_path / "incoming"
    incoming.mkdir()
    (incoming / "0").write_bytes(panel())
    e = lib.add_upload([("mat.png", incoming / "0")])
    assert e.path.name == "mat.png" and e.path.read_bytes() == panel()
    assert not (incoming / "0").exists() and lib.textures(e.id).shape == (10, 16, 16)
    (incoming / "1").write_bytes(b"\0" * ((1 << 20) + 1))
    with pytest.raises(MaterialError, match="upload of 1 MB is over the viewer's 1 MB limit"):
        lib.add_upload([("big.png", incoming / "1")])
    assert sorted(p.name for p in (tmp_path / "uploads").rglob("*.png")) == ["mat.png"]


def solid(rgb: tuple[int, int, int], size: int = 16) -> np.ndarray:
    return np.full((size, size, 3), np.array(rgb, np.float32) / 255.0, np.float32)


def test_gallery_pictures_of_file_materials_are_their_colour_maps_and_kept(tmp_path):
    """A 5-panel file shows its diffuse panel, a spec-gloss folder its diffuse map, a
    metal-rough folder its base colour (a metal is not black); a colour map Pillow cannot
    show (EXR) falls back to the material's diffuse map. Pictures are made once, on their
    own thread, so a frame in the works does not hold them back."""
    import asyncio
    import threading
    from types import SimpleNamespace

    from render_jobs.materials.maps import linear_to_srgb
    from tests.test_material_libraries import write
    from trainer.rendering.viewer.app import THUMB, THUMB_NICE
    from trainer.rendering.viewer.app import Viewer as App

    lib_dir = tmp_path / "lib"
    strip = np.concatenate([solid(c) for c in [(9, 9, 9), (128, 128, 255), (200, 30, 40),
                                                (90, 90, 90), (20, 20, 20)]], 1)  # fmt: skip
    write(lib_dir / "five.png", strip)
    write(lib_dir / "gloss" / "a_diffuse.png", solid((10, 200, 30)))
    write(lib_dir / "gloss" / "a_specular.png", solid((40, 40, 40)))
    write(lib_dir / "gloss" / "a_glossiness.png", solid((100, 100, 100))[..., 0])
    write(lib_dir / "metal" / "b_Color.png", solid((230, 180, 60)))
    write(lib_dir / "metal" / "b_Metalness.png", np.ones((16, 16), np.float32))
    write(lib_dir / "metal" / "b_Roughness.png", solid((60, 60, 60))[..., 0])
    write(lib_dir / "exr" / "c_Color.exr", solid((255, 255, 255)) * 0.2)
    write(lib_dir / "exr" / "c_Roughness.png", solid((60, 60, 60))[..., 0])
    lib = Library([], [str(lib_dir)], tmp_path / "uploads")
    by_label = {e.label: e.id for e in lib.entries.values()}
    viewer = App(SimpleNamespace(library=lib), tmp_path / "uploads", {})
    try:
        grey = round(255 * float(linear_to_srgb(np.float32(0.2))))  # EXR colour is linear
        want = {"five.png": (200, 30, 40), "gloss": (10, 200, 30), "metal": (230, 180, 60),
                "exr": (grey, grey, grey)}  # fmt: skip
        for label, rgb in want.items():
            body = viewer.thumb(by_label[label])
            pic = np.asarray(Image.open(io.BytesIO(body)))
            assert pic.shape[2] == 3 and max(pic.shape[:2]) <= THUMB
            assert np.abs(pic.astype(int) - rgb).max() <= 1, (label, pic[0, 0])
        (lib_dir / "five.png").unlink()
        assert viewer.thumb(by_label["five.png"]) == viewer.thumb(by_label["five.png"])  # kept
        if sys.platform.startswith("linux"):  # the pictures' thread yields to frames
            nice = viewer.thumb_pool.submit(
                lambda: os.getpriority(os.PRIO_PROCESS, threading.get_native_id())
            ).result()
            assert nice == min(19, os.getpriority(os.PRIO_PROCESS, 0) + THUMB_NICE)

        busy, done = threading.Event(), threading.Event()
        viewer.pool.submit(busy.wait, 30)  # a long frame on the frames thread
        fresh = App(SimpleNamespace(library=lib), tmp_path / "uploads", {})
        fresh.pool = viewer.pool

        async def picture():
            body = await fresh.run(fresh.thumb, by_label["gloss"], pool=fresh.thumb_pool)
            done.set()
            return body

        assert asyncio.run(asyncio.wait_for(picture(), 20))[:4] == b"\x89PNG"
        assert done.is_set() and not busy.is_set()  # made while the frame was still running
        busy.set()
        fresh.thumb_pool.shutdown()
    finally:
        viewer.close()


# ---- the server --------------------------------------------------------------------------------


class Viewer(ServerProcess):
    """``trainer viewer`` in a subprocess on a port of its own."""

    def __init__(self, *args, host="127.0.0.1", tmp: Path | None = None):
        env = {**os.environ, **({"TMPDIR": str(tmp)} if tmp else {})}
        cmd = [BIN / "trainer", "viewer", *args, "--host", host, "--device", "cpu"]
        super().__init__(cmd, "viewer", env)

    def get(self, path: str, headers: dict | None = None, data: bytes | None = None):
        req = urllib.request.Request(self.base + path, headers=headers or {}, data=data)
        try:
            with urllib.request.urlopen(req, timeout=60) as r:
                return r.status, r.read(), dict(r.headers)
        except urllib.error.HTTPError as e:
            return e.code, e.read(), dict(e.headers)

    def upload(self, files: list[tuple[str, bytes]], secret: str | None):
        boundary = uuid.uuid4().hex
        body = (
            b"".join(
                f"--{boundary}\r\nContent-Disposition: form-data; "
                f'name="file"; filename="{name}"\r\n'
                f"Content-Type: application/octet-stream\r\n\r\n".encode()
                + data
                + b"\r\n"
                for name, data in files
            )
            + f"--{boundary}--\r\n".encode()
        )
        headers = {"Content-Type": f"multipart/form-data; boundary={boundary}"}
        if secret:
            headers["X-Shaderball-Secret"] = secret
        return self.get("/api/upload", headers, body)

    def secret(self) -> str:
        page = self.get("/")[1].decode()
        return page.split('name="secret" content="')[1].split('"')[0]


@pytest.fixture(scope="module")
def run(tiny_store, tmp_path_factory) -> Path:
    """A checkpoint trained briefly on the tiny real store (it carries the store's layout),
    with a moving average of its weights, which it renders with."""
    out = tmp_path_factory.mktemp("viewer") / "run"
    r = subprocess.run(
        [str(BIN / "trainer"), "train", "--store", tiny_store.url, "--out", str(out), "--loss",
         "l1", "--epochs", "1", "--batch-size", "4", "--workers", "0", "--max-steps", "6",
         "--width", "16", "--ema-decay", "0.9"],
        capture_output=True, text=True,
    )  # fmt: skip
    assert r.returncode == 0, r.stderr[-2000:]
    return out


def frame_query(m: str, **extra) -> str:
    from urllib.parse import urlencode

    return "/api/frame?" + urlencode({"m": m, "az": 200, "el": 35, "t": 3, **extra})


def snapshot(*folders: Path) -> dict[str, str]:
    """Every file under ``folders`` with the SHA-256 of its bytes."""
    return {
        str(p): hashlib.sha256(p.read_bytes()).hexdigest()
        for f in folders
        for p in sorted(Path(f).rglob("*"))
        if p.is_file()
    }


def test_a_gallery_store_out_of_reach_stops_the_viewer_in_one_line(run):
    from tests.conftest import free_port, s3_env

    env = {**os.environ, **s3_env(f"http://127.0.0.1:{free_port()}", AWS_MAX_ATTEMPTS="1",
                                  SHADERBALL_STORE_RETRY_S="1")}  # fmt: skip
    r = subprocess.run([str(BIN / "trainer"), "viewer", "--checkpoint", str(run), "--store",
                        "s3://shaderball/gone.zarr"], env=env, capture_output=True, text=True,
                       timeout=120)  # fmt: skip
    assert r.returncode == 1 and "Traceback" not in r.stderr, r.stderr[-3000:]
    last = r.stderr.strip().splitlines()[-1]
    assert last.startswith("Error: StoreUnreachable: ") and "127.0.0.1" in last, last


@pytest.mark.slow
def test_the_server_answers_bad_requests_in_one_line_and_goes_on(run, tiny_store, tmp_path):
    before = snapshot(run, Path(tiny_store.url))
    with Viewer("--checkpoint", run, "--store", tiny_store.url, "--max-upload-mb", "64",
                tmp=tmp_path) as v:  # fmt: skip
        assert "step 6 · averaged weights ·" in v.get("/")[1].decode()  # the run's average
        secret = v.secret()
        status, body, _ = v.upload([("panel.png", panel())], secret=None)
        assert status == 403  # a POST without the page's secret
        for files, culprit in BAD_UPLOADS:
            status, body, _ = v.upload(files, secret)
            err = json.loads(body)["error"]
            assert status == 400 and culprit in err and "\n" not in err, err
        status, body, _ = v.upload([("big.png", b"\0" * (65 << 20))], secret)
        assert status == 413 and "64 MB limit" in json.loads(body)["error"]
        status, body, _ = v.upload([("panel.png", panel())], secret)
        assert status == 200
        up = json.loads(body)["id"]
        kept = [p.relative_to(tmp_path) for p in tmp_path.rglob("*") if p.is_file()]
        assert len(kept) == 1 and kept[0].name == "panel.png", kept  # only the good upload
        assert kept[0].parts[0].startswith("shaderball-viewer-")
        status, body, headers = v.get(frame_query(up))
        assert status == 200 and headers["Content-Type"] == "image/jpeg"
        assert "net;dur=" in headers["Server-Timing"]
        for query, culprit in [
            (frame_query("s0:999"), "s0:999: no such material"),
            (frame_query("s0:1", el="-4"), "el=-4"),
            (frame_query("s0:1", roughness_scale="9"), "roughness_scale=9 is outside"),
            (frame_query("/etc/passwd"), "/etc/passwd: no such material"),
        ]:
            status, body, _ = v.get(query)
            assert status == 400 and culprit in json.loads(body)["error"], body
        # the PNG keeps the material and the light
        status, body, headers = v.get(frame_query("s0:1", fmt="png", download="1", tiling="2"))
        assert status == 200 and "attachment" in headers["Content-Disposition"]
        meta = Image.open(io.BytesIO(body)).text
        material = json.loads(meta["shaderball:material"])
        light = json.loads(meta["shaderball:light"])
        assert material["id"] == "s0:1" and material["edits"]["tiling"] == 2.0
        assert light["azimuth"] == 200 and light["turbidity"] == 3
        status, body, _ = v.get("/api/truth?m=s0:1&k=2")
        truth = json.loads(body)
        assert status == 200 and truth["psnr"] > 5 and truth["truth"].startswith("data:image/png")
    assert not any(tmp_path.iterdir())  # the temporary folder goes with the server
    assert snapshot(run, Path(tiny_store.url)) == before  # nothing written beside them


@pytest.mark.slow
def test_off_loopback_the_viewer_needs_a_token(run):
    with Viewer("--checkpoint", run, host="0.0.0.0") as v:
        assert v.get("/")[0] == 401
        out, err = v.stop()
    assert "token (needed by every request from another machine)" in out + err
    with Viewer("--checkpoint", run, "--token", "s3cret", host="0.0.0.0") as v:
        assert v.get("/")[0] == 401
        assert v.get("/?token=s3cret")[0] == 200
        assert v.get("/api/materials", {"Authorization": "Bearer s3cret"})[0] == 200


@pytest.mark.slow
def test_the_viewer_runs_an_exported_model_as_its_checkpoint(run, tiny_store, tmp_path):
    """``--checkpoint ball.onnx``: the header says ONNX Runtime, and a stored material, an
    edit and an upload (mapped with the layout beside the model) give the checkpoint's frames."""
    model = tmp_path / "ball.onnx"
    r = subprocess.run([str(BIN / "trainer"), "export", "--checkpoint", str(run), "-o",
                        str(model)], capture_output=True, text=True)  # fmt: skip
    assert r.returncode == 0, r.stderr[-2000:]
    frames = []
    for source in (run, model):
        with Viewer("--checkpoint", source, "--store", tiny_store.url) as v:
            page = v.get("/")[1].decode()
            assert ("cpu · ONNX Runtime" in page) == (source == model), page[:600]
            status, body, _ = v.upload([("panel.png", panel())], v.secret())
            assert status == 200, body
            up = json.loads(body)["id"]
            got = []
            for query in (frame_query("s0:1"), frame_query("s0:2", roughness_scale="0.5"),
                          frame_query(up, tiling="2")):  # fmt: skip
                status, body, _ = v.get(query + "&fmt=png")
                assert status == 200, body
                got.append(np.asarray(Image.open(io.BytesIO(body)), np.int16))
            frames.append(got)
    for checkpoint_frame, model_frame in zip(*frames, strict=True):
        assert checkpoint_frame.std() > 1
        assert np.abs(checkpoint_frame - model_frame).max() <= 1  # 8-bit rounding at most


DIGEST = """async () => {
  const img = document.getElementById('frame');
  const bytes = new Uint8Array(await (await fetch(img.src)).arrayBuffer());
  let h = 0;
  for (const b of bytes) h = (h * 31 + b) >>> 0;
  return bytes.length + ':' + h;
}"""


def frames(page) -> int:
    return int(page.locator("#frame").get_attribute("data-frames"))


def wait_new_frame(page, after: int, timeout: float = 60_000) -> None:
    page.wait_for_function(
        f"parseInt(document.getElementById('frame').dataset.frames) > {after}", timeout=timeout
    )


@pytest.mark.slow
def test_the_page_in_chromium_drags_the_sun_edits_uploads_and_compares(run, tiny_store, tmp_path):
    from playwright.sync_api import sync_playwright

    (tmp_path / "good.png").write_bytes(panel(32))
    (tmp_path / "broken.png").write_bytes(panel(32)[:500])
    with Viewer("--checkpoint", run, "--store", tiny_store.url, tmp=tmp_path / "t") as v, \
            sync_playwright() as p:  # fmt: skip
        browser = p.chromium.launch(executable_path=chromium(), args=["--no-sandbox"])
        page = browser.new_page(viewport={"width": 1400, "height": 1000})
        errors, failed = [], []
        page.on("pageerror", lambda e: errors.append(str(e)))
        page.on("console", lambda m: m.type == "error" and failed.append(m.text))
        page.goto(v.base + "/")
        wait_new_frame(page, 0)
        first = page.evaluate(DIGEST)
        assert "network" in page.locator("#timing").inner_text()

        # drag the sun across the hemisphere: the image follows while dragging
        box = page.locator("#sky").bounding_box()
        cx, cy = box["x"] + box["width"] / 2, box["y"] + box["height"] / 2
        n = frames(page)
        page.mouse.move(cx - 60, cy + 40)
        page.mouse.down()
        for k in range(1, 9):
            page.mouse.move(cx - 60 + 14 * k, cy + 40 - 8 * k)
            time.sleep(0.15)
        wait_new_frame(page, n + 1)  # frames came while the button was still down
        page.mouse.up()
        page.wait_for_timeout(1500)
        dragged = page.evaluate(DIGEST)
        assert dragged != first
        assert "azimuth" in page.locator("#light-v").inner_text()

        # rougher: the image changes again
        n = frames(page)
        page.locator("#roughness_scale").fill("2.5")
        wait_new_frame(page, n)
        page.wait_for_timeout(1000)
        assert page.evaluate(DIGEST) != dragged

        # the sun turns round the sky by itself, as fast as frames come, until stopped
        n, light = frames(page), page.locator("#light-v").inner_text()
        page.click("#turn")
        wait_new_frame(page, n + 3)
        page.wait_for_function(
            "document.getElementById('turn-rate').textContent.endsWith(' frames/s')"
        )
        assert page.locator("#light-v").inner_text() != light
        page.click("#turn")
        light = page.locator("#light-v").inner_text()
        page.wait_for_timeout(700)
        assert page.locator("#light-v").inner_text() == light
        assert page.locator("#turn-rate").inner_text() == ""

        # a stored sun shows the Cycles ground truth beside the network (edits reset first)
        page.click("#reset")
        page.click("#suns button >> nth=0")
        page.wait_for_selector("#truth", state="visible", timeout=60_000)
        assert "dB" in page.locator("#truth-psnr").inner_text()
        page.wait_for_timeout(1000)
        ARTIFACTS.mkdir(exist_ok=True)
        page.screenshot(path=str(ARTIFACTS / "viewer.png"), full_page=True)
        assert not failed, failed  # every request so far answered, the tab's icon included

        # a broken upload: the loader's one line in the page; a good one: a new material
        tiles = page.locator(".tile").count()
        page.set_input_files("#upload", str(tmp_path / "broken.png"))
        page.click("#upload-go")
        page.wait_for_function("document.getElementById('upload-msg').textContent !== ''")
        message = page.locator("#upload-msg").inner_text()
        assert "broken.png" in message and "\n" not in message.strip(), message
        n = frames(page)
        before = page.evaluate(DIGEST)
        page.set_input_files("#upload", str(tmp_path / "good.png"))
        page.click("#upload-go")
        page.wait_for_function(
            "document.getElementById('upload-msg').textContent.includes('loaded')"
        )
        wait_new_frame(page, n)
        page.wait_for_timeout(1000)
        assert page.locator(".tile").count() == tiles + 1
        assert page.locator("#gallery-count").inner_text() == str(tiles + 1)
        assert page.evaluate(DIGEST) != before
        assert "good.png" in page.locator("#material").inner_text()

        # a frame that takes long (held here) dims the image and says so, until it comes
        held = []
        page.route("**/api/frame?*", lambda route: held.append(route))
        n = frames(page)
        page.locator(".tile >> nth=1").click()
        page.wait_for_function("document.getElementById('frame').classList.contains('waiting')")
        assert "working" in page.locator("#timing").inner_text()
        page.wait_for_function(  # the time waited so far counts up
            "parseFloat((/working… ([0-9.]+) s/.exec("
            "document.getElementById('timing').textContent) || [0, 0])[1]) >= 0.8"
        )
        page.screenshot(path=str(ARTIFACTS / "viewer-working.png"))
        for route in held:
            route.continue_()
        page.unroute("**/api/frame?*")
        wait_new_frame(page, n)
        page.wait_for_timeout(300)  # the counter has stopped: it does not write over the times
        assert "network" in page.locator("#timing").inner_text()
        assert page.evaluate("!document.getElementById('frame').classList.contains('waiting')")
        browser.close()
        assert not errors, errors
