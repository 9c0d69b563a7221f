"""Pictures the command lines write: the format from the name, checked first; whole files."""

from __future__ import annotations

import numpy as np
import pytest
from PIL import Image, ImageSequence

from storage.image_files import image_format, save_animation, save_image


def _picture(value: int, size: int = 16) -> Image.Image:
    ramp = np.linspace(0, 255, size * size * 3).reshape(size, size, 3)
    return Image.fromarray(((ramp + value) % 256).astype(np.uint8))


def test_the_format_comes_from_the_name_and_a_bad_name_is_refused_naming_it(tmp_path):
    assert image_format("a/b.PNG") == "PNG" and image_format("c.jpeg") == "JPEG"
    assert image_format("d.webp", animated=True) == "WEBP"
    with pytest.raises(ValueError) as bad:
        image_format("x.foo")
    assert (
        str(bad.value)
        == "'x.foo' does not name a picture: its name must end in .png, .jpg, .jpeg or .webp"
    )
    with pytest.raises(ValueError, match=r"'x.jpg' does not name an animation: .*\.gif"):
        image_format("x.jpg", animated=True)
    with pytest.raises(ValueError, match="does not name a picture"):
        save_image(_picture(0), tmp_path / "x.tiff")
    assert list(tmp_path.iterdir()) == []


def test_pictures_are_written_whole_with_their_text(tmp_path):
    out = tmp_path / "sub" / "p.png"
    save_image(_picture(0), out, {"shaderball:light": '{"turbidity": 3}'})
    with Image.open(out) as im:
        assert im.info["shaderball:light"] == '{"turbidity": 3}'
        assert np.array_equal(np.asarray(im), np.asarray(_picture(0)))
    before = out.read_bytes()
    with pytest.raises(OSError):  # PNG cannot hold CMYK: the save fails half way
        save_image(Image.new("CMYK", (8, 8)), out)
    assert out.read_bytes() == before and [p.name for p in out.parent.iterdir()] == ["p.png"]
    save_image(_picture(9), tmp_path / "p.jpg")
    with Image.open(tmp_path / "p.jpg") as im:
        assert im.format == "JPEG" and im.size == (16, 16)


@pytest.mark.parametrize("suffix", [".png", ".gif", ".webp"])
def test_animations_keep_every_frame_loop_and_their_rate(tmp_path, suffix):
    frames = [_picture(40 * k) for k in range(5)]
    out = tmp_path / f"a{suffix}"
    save_animation(frames, out, fps=10, text={"shaderball:light": "{}"})
    with Image.open(out) as im:
        assert im.n_frames == 5 and im.info["loop"] == 0
        got = [np.asarray(f.convert("RGB"), np.int16) for f in ImageSequence.Iterator(im)]
        durations = []
        for k in range(5):
            im.seek(k)
            im.load()  # WebP says a frame's duration once it is decoded
            durations.append(im.info["duration"])
        assert durations == [100] * 5
        if suffix == ".png":  # lossless, with its text
            assert im.info["shaderball:light"] == "{}"
            assert all(np.array_equal(g, np.asarray(f)) for g, f in zip(got, frames, strict=True))
    with pytest.raises(ValueError, match="at least one frame"):
        save_animation([], tmp_path / f"b{suffix}", fps=10)
