"""Real training runs on a real rendered store: in-process, torchrun (gloo), kill + resume."""

from __future__ import annotations

import contextlib
import csv
import dataclasses
import json
import os
import re
import shlex
import signal
import subprocess
import sys
import time
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import psutil
import pytest
import torch
from click.testing import CliRunner
from PIL import Image, ImageSequence

from storage.schema import Layout
from storage.writer import create_store, write_shard
from tests.flaky_proxy import FlakyProxy
from tests.storage_helpers import synthetic_payload
from tests.test_trainer import vgg_weights_file
from trainer import checkpoint, runfiles
from trainer.cli import main as trainer_main
from trainer.model import ModelConfig, NeuralRenderer
from trainer.rendering.evaluate import evaluate
from trainer.rendering.infer import Renderer
from trainer.rendering.load import load_renderer
from trainer.targets import Tonemap, model_inputs
from trainer.training import train as train_module
from trainer.training.config import TrainConfig
from trainer.training.data import Catalog, ShardStream, loader, steps_left
from trainer.training.train import RunError, TrainingDiverged, train
from trainer.training.validation import Validator

pytestmark = pytest.mark.slow

# the paper's recipe (these tests are of the run's mechanics; the default recipe's own are at
# the end), width 16: the U-Net's layout at a sixteenth of the paper's cost
BASE = {"recipe": "paper", "loss": "l1", "width": 16, "batch_size": 2, "holdout_fraction": 0.25,
        "workers": 0, "log_every": 2}  # fmt: skip


def config(store, out, **kw) -> TrainConfig:
    return TrainConfig(**{"store": (store.url,), "out": str(out), **BASE, **kw})


def argv(store, out, **kw) -> list[str]:
    from trainer.training.config import to_argv

    return to_argv(config(store, out, **kw))


def run_group(cmd: list[str], env: dict | None = None, timeout: float = 300):
    """Run ``cmd`` in its own process group; on a timeout kill the whole group (torchrun and
    its ranks), so that a hung run leaves nothing behind."""
    proc = subprocess.Popen(
        cmd, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
        start_new_session=True,
    )  # fmt: skip
    try:
        out, err = proc.communicate(timeout=timeout)
    except subprocess.TimeoutExpired:
        os.killpg(proc.pid, signal.SIGKILL)
        proc.communicate()
        raise
    return subprocess.CompletedProcess(cmd, proc.returncode, out, err)


def private_tmp(tmp_path: Path, env: dict | None = None) -> tuple[dict, Path]:
    """An environment whose $TMPDIR is a fresh folder, to see what a launch leaves there."""
    tmp = tmp_path / "tmpdir"
    tmp.mkdir()
    return {**(env or os.environ), "TMPDIR": str(tmp)}, tmp


def torchelastic_left(tmp: Path) -> list[str]:
    return [p.name for p in tmp.glob("torchelastic_*")]


def sample_lines(run: Path, rank: int = 0) -> list[str]:
    return (run / "samples" / f"rank-{rank}.txt").read_text().splitlines()


def mean_l1(model: NeuralRenderer, catalog: Catalog) -> float:
    split = catalog.split("train")
    stream = ShardStream(split, batch=8, seed=0, buffer=8)
    model.eval()
    losses = []
    with torch.no_grad():
        for b in stream:
            pred = model(model_inputs(b["maps"]), b["light"])
            losses.append(float((pred - Tonemap()(b["render"])).abs().mean()))
    return float(np.mean(losses))


@pytest.fixture(scope="module")
def trained(tiny_store, tmp_path_factory):
    """A short L1 run (6 epochs, batch 2) on the tiny store: its folder."""
    out = tmp_path_factory.mktemp("run") / "run"
    train(config(tiny_store, out, epochs=6, workers=2))
    return out


def test_training_lowers_the_loss(tiny_store, trained):
    state = checkpoint.load(trained)
    catalog = Catalog.from_dict(state["catalog"])
    torch.manual_seed(0)  # the run's initial weights
    before = mean_l1(NeuralRenderer(ModelConfig(**state["model_config"])), catalog)
    after = mean_l1(Renderer.from_checkpoint(trained).model, catalog)
    assert after < 0.7 * before, (before, after)
    assert state["step"] == 6 * 9 and state["epoch"] == 6 and state["position"] == 0
    assert len(checkpoint.listing(trained)) <= 3
    log = [json.loads(line) for line in (trained / "log.jsonl").read_text().splitlines()]
    assert log[-1]["step"] == 54 and all(0 <= r["data_wait"] <= 1 for r in log)
    assert sum(r["steps"] for r in log) == 54  # every step in one line, epoch tails included
    assert [r["step"] for r in log[:6]] == [2, 4, 6, 8, 9, 10]  # 9 steps an epoch, log_every 2
    assert list((trained / "tb").glob("events.out.tfevents.*"))
    assert {r["lr"] for r in log} == {1e-3}  # the constant schedule


def test_a_run_without_a_terminal_writes_its_bar_as_lines(
    tiny_store, tmp_path, capsys, monkeypatch
):
    """Where stderr is no terminal (a pod's log, a file), rank 0's bar is whole lines with the
    log's figures, not carriage returns (``shaderball.progress``)."""
    from shaderball import progress

    monkeypatch.setattr(progress, "PLAIN_EVERY", 0.0)  # a line at every redraw
    train(config(tiny_store, tmp_path / "r", epochs=2, max_steps=12, val_samples=0))
    err = capsys.readouterr().err
    bars = [ln for ln in err.splitlines() if ln.startswith("epoch ")]
    assert "\r" not in err and bars[0].startswith("epoch 1/2:   0%|")
    assert any("img_s=" in ln and "loss=" in ln for ln in bars)  # the log's figures ride along
    assert bars[-1].startswith("epoch 2/2:") and " 3/9 " in bars[-1]  # stopped at step 12 of 18
    monkeypatch.setattr(progress, "PLAIN_EVERY", 3600.0)  # a short run: no line at all
    train(config(tiny_store, tmp_path / "s", epochs=2, val_samples=0))
    assert "epoch " not in capsys.readouterr().err


def test_eval_scores_the_training_materials_when_asked(trained, tmp_path):
    """``--trained``: every sample of the materials the run trained on, said so, and the run's
    kept held-out scores (eval.json) left as they were; refused beside --on or a second
    checkpoint."""
    catalog = Catalog.from_dict(checkpoint.load(trained)["catalog"])
    kept = trained / "eval.json"
    before = kept.read_text() if kept.exists() else None
    r = CliRunner().invoke(trainer_main, ["eval", "--checkpoint", str(trained), "--trained"])
    assert r.exit_code == 0, r.output
    n = len(catalog.split("train"))
    assert n == 3 * (8 - len(catalog.heldout[0])) and f": {n} training samples of " in r.output
    assert (kept.read_text() if kept.exists() else None) == before
    r = CliRunner().invoke(
        trainer_main, ["eval", "--checkpoint", str(trained), "--trained", "--json"]
    )
    result = json.loads(r.output[r.output.index("{") :])
    assert result["split"] == "train" and result["samples"] == n
    for extra in (["--on", str(tmp_path)], ["--checkpoint", str(trained)]):
        args = ["eval", "--checkpoint", str(trained), "--trained", *extra]
        r = CliRunner().invoke(trainer_main, args)
        assert r.exit_code == 2 and "--trained" in r.output and "not with --on" in r.output


def test_eval_and_render(tiny_store, trained, tmp_path):
    r = CliRunner().invoke(
        trainer_main,
        ["eval", "--checkpoint", str(trained), "--json", "--grid", str(tmp_path / "g.png")],
    )
    assert r.exit_code == 0, r.output
    assert "batch/s" not in r.output  # no progress bar where stderr is not a terminal
    result = json.loads(r.output[r.output.index("{") :])
    held = Catalog.from_dict(checkpoint.load(trained)["catalog"]).heldout[0]
    assert result["samples"] == 3 * len(held) == result["overall"]["n"]
    assert result["overall"]["materials"] == len(held)
    few = len(held) < 5  # no interval under 5 materials (trainer.intervals.MIN_MATERIALS)
    o = result["overall"]
    assert (o["psnr_low"] is None) if few else (o["psnr_low"] <= o["psnr"] <= o["psnr_high"])
    assert sum(m["n"] for m in result["by_kind"].values()) == result["samples"]
    assert 5 < result["overall"]["psnr"] < 60 and 0 < result["overall"]["ssim"] <= 1
    assert 0 < result["overall"]["flip"] < 1  # NVIDIA's FLIP: 0 only for identical images
    rows = min(4, result["samples"])  # --grid-count 4; 3 panels a row, enlarged 4x to 256²
    assert Image.open(tmp_path / "g.png").size == (3 * 256, 24 + rows * 256)  # under a header
    kept = json.loads((trained / "eval.json").read_text())  # for the dashboard's runs page
    assert kept["overall"] == result["overall"]
    # the held-out scores the run kept at each epoch's end: the last, of the final weights,
    # is what eval says of them (every held-out sample: fewer than --val-samples)
    val = [json.loads(line) for line in (trained / "val.jsonl").read_text().splitlines()]
    assert [r["step"] for r in val] == [9 * e for e in range(1, 7)]
    assert [r["epoch"] for r in val] == list(range(6))
    assert all(r["samples"] == result["samples"] for r in val)
    assert val[-1]["psnr"] == pytest.approx(result["overall"]["psnr"], abs=2e-3)
    assert val[-1]["ssim"] == pytest.approx(result["overall"]["ssim"], abs=2e-4)
    # each epoch's score is of that epoch's weights (whether 54 steps of a width-16 network
    # raise the held-out score of 6 samples is chance: test_training_lowers_the_loss)
    assert len({r["psnr"] for r in val}) == len(val)
    # val.png: the last score's first 3 samples, drawn as eval's grid (64² enlarged to 256²)
    assert Image.open(trained / "val.png").size == (3 * 256, 24 + 3 * 256)
    # checkpoints/best.pt: the checkpoint of the best score, whatever the rotation dropped
    best = max(val, key=lambda x: x["psnr"])
    state = checkpoint.load(trained / "checkpoints" / "best.pt")
    assert state["step"] == best["step"] and state["best"] == {k: best[k] for k in ("step", "psnr")}
    assert checkpoint.load(trained)["best"] == state["best"]

    out = tmp_path / "a.png"
    args = ["render", "--checkpoint", str(trained), "--store", tiny_store.url, "--sample", "4"]
    assert CliRunner().invoke(trainer_main, [*args, "-o", str(out)]).exit_code == 0
    other = tmp_path / "b.png"
    r = CliRunner().invoke(
        trainer_main, [*args, "--sun", "0.8,0,0.2", "--turbidity", "8", "-o", str(other)]
    )
    assert r.exit_code == 0, r.output
    a, b = np.asarray(Image.open(out)), np.asarray(Image.open(other))
    assert a.shape == (64, 64, 3) and np.abs(a.astype(int) - b).mean() > 0  # the sun matters
    assert json.loads(Image.open(other).info["shaderball:light"])["turbidity"] == 8
    assert json.loads(Image.open(out).info["shaderball:material"]) == {
        "store": tiny_store.url, "sample": 4,
    }  # fmt: skip

    # the sun once round at the sample's own elevation: frame 0 is the still above
    sweep = tmp_path / "sweep.png"
    r = CliRunner().invoke(trainer_main, [*args, "--sweep", "6", "--fps", "5", "-o", str(sweep)])
    assert r.exit_code == 0, r.output
    with Image.open(sweep) as im:
        assert im.n_frames == 6 and im.info["duration"] == 200
        assert json.loads(im.info["shaderball:light"])["sweep"] == 6
        frames = [np.asarray(f.convert("RGB"), int) for f in ImageSequence.Iterator(im)]
    assert np.abs(frames[0] - a).max() <= 1  # batched against alone: float rounding at most
    assert min(np.abs(f - frames[0]).mean() for f in frames[1:]) > 0
    for bad, needle in [
        ([*args, "-o", str(tmp_path / "x.foo")], f"-o: '{tmp_path / 'x.foo'}' does not name"),
        ([*args, "--sweep", "6", "-o", str(tmp_path / "x.jpg")], "does not name an animation"),
        (["eval", "--checkpoint", str(trained), "--grid", str(tmp_path / "g.bmp")], "--grid"),
        (["eval", "--checkpoint", str(trained), "--batch-size", "0"], "'--batch-size': 0 is not"),
        (["eval", "--checkpoint", str(trained), "--grid-count", "-1"], "'--grid-count': -1 is"),
    ]:
        r = CliRunner().invoke(trainer_main, bad)
        assert r.exit_code == 2 and needle in r.output, r.output
    assert not list(tmp_path.glob("x.*")) and not (tmp_path / "g.bmp").exists()
    no_grid = ["eval", "--checkpoint", str(trained), "--grid-count", "0"]
    r = CliRunner().invoke(trainer_main, [*no_grid, "--grid", str(tmp_path / "none.png")])
    assert r.exit_code == 0 and "grid:" not in r.output and not (tmp_path / "none.png").exists()

    # the Python API: one material under two suns at once, as the CLI did
    renderer = Renderer.from_checkpoint(trained, "cpu")
    maps = tiny_store.packed_maps(1)
    two = renderer.render(np.stack([maps, maps]), [(0, 0, 1), (0.8, 0, 0.2)], [3, 8])
    assert two.shape == (2, 3, 64, 64) and not np.allclose(two[0], two[1])
    with pytest.raises(ValueError, match="maps have shape"):
        renderer.render(maps[:, :32, :32].copy(), (0, 0, 1), 3)


def test_export_onnx_renders_as_the_checkpoint_and_a_failed_check_writes_nothing(
    tiny_store, trained, tmp_path, monkeypatch
):
    """``trainer export``: ONNX Runtime, fed stored maps and suns of the store, renders as
    the torch renderer does, at a batch size the export never saw; the screen UV layout lies
    beside the model; a model that fails the check leaves the old file as it was."""
    import onnxruntime as ort

    from render_jobs.screen_uv import ScreenUV
    from trainer.rendering import export

    out = tmp_path / "m" / "ball.onnx"
    r = CliRunner().invoke(trainer_main, ["export", "--checkpoint", str(trained), "-o", str(out)])
    assert r.exit_code == 0, r.output
    assert f"wrote {out} (" in r.output and "ONNX Runtime renders it within" in r.output
    session = ort.InferenceSession(str(out), providers=["CPUExecutionProvider"])
    assert [(i.name, i.type, i.shape[1:]) for i in session.get_inputs()] == [
        ("maps", "tensor(uint8)", [11, 64, 64]), ("sun", "tensor(float)", [3]),
        ("turbidity", "tensor(float)", []),
    ]  # fmt: skip
    assert isinstance(session.get_inputs()[0].shape[0], str)  # any batch size
    meta = session.get_modelmeta().custom_metadata_map
    assert meta["shaderball.resolution"] == "64" and meta["shaderball.weights"] == "trained"
    with pytest.raises(checkpoint.CheckpointError, match="holds the one set of weights"):
        load_renderer(out, weights="trained")
    assert json.loads(meta["shaderball.tonemap"]) == checkpoint.load(trained)["tonemap"]
    samples = [0, 4, 7, 9, 13]  # five materials' stored maps, under their own suns
    maps = np.stack(
        [tiny_store.packed_maps(tiny_store.layout.material_of_sample(i)) for i in samples]
    )
    lights = [tiny_store.light(i) for i in samples]
    sun = np.array([d for d, _ in lights], np.float32)
    turbidity = np.array([t for _, t in lights], np.float32)
    (got,) = session.run(["image"], {"maps": maps, "sun": sun, "turbidity": turbidity})
    want = Renderer.from_checkpoint(trained, "cpu").render(maps, sun, turbidity)
    assert got.shape == want.shape == (5, 3, 64, 64) and np.abs(got - want).max() < 1e-4
    layout = ScreenUV.from_bytes((tmp_path / "m" / "ball.screen_uv.npz").read_bytes())
    kept = ScreenUV.from_bytes(checkpoint.load(trained)["screen_uv"])
    assert layout.meta() == kept.meta() and np.array_equal(layout.uv, kept.uv)

    before = out.read_bytes()
    monkeypatch.setattr(export, "TOLERANCE", -1.0)  # no model can pass
    r = CliRunner().invoke(trainer_main, ["export", "--checkpoint", str(trained), "-o", str(out)])
    assert r.exit_code == 1 and len(r.stderr.splitlines()) == 2  # progress, then the error
    assert re.fullmatch(
        r"Error: the exported model renders up to \S+ away from the checkpoint \(allowed "
        r"-1e\+00\); nothing written", r.stderr.splitlines()[1]
    )  # fmt: skip
    assert out.read_bytes() == before
    assert sorted(p.name for p in out.parent.iterdir()) == ["ball.onnx", "ball.screen_uv.npz"]
    blocked = tmp_path / "file"
    blocked.write_text("")
    r = CliRunner().invoke(
        trainer_main, ["export", "--checkpoint", str(trained), "-o", str(blocked / "b.onnx")]
    )
    assert r.exit_code == 1 and len(r.stderr.splitlines()) == 2, r.stderr
    assert r.stderr.splitlines()[1].startswith(
        f"Error: FileExistsError: [Errno 17] File exists: '{blocked}'"
    )


def test_export_at_an_older_opset_renders_as_the_checkpoint(tiny_store, trained, tmp_path):
    """``--opset 15`` (Unity Sentis 1.x reads no newer) writes opset 15 through the other
    exporter, with the same metadata, and renders a store's maps as the torch renderer does;
    an opset outside the offered range is a usage error that names it."""
    import onnx
    import onnxruntime as ort

    from trainer.rendering import export

    out = tmp_path / "ball-15.onnx"
    args = ["export", "--checkpoint", str(trained), "-o", str(out), "--opset", "15"]
    r = CliRunner().invoke(trainer_main, args)
    assert r.exit_code == 0, r.output
    assert "ONNX opset 15)" in r.output
    model = onnx.load(str(out))
    assert {o.domain: o.version for o in model.opset_import}[""] == 15
    assert {p.key for p in model.metadata_props} >= {"shaderball.resolution", "shaderball.tonemap"}
    maps = np.stack([tiny_store.packed_maps(m) for m in range(3)])
    sun = np.array([[0.3, -0.2, 0.9], [0, 0, 1], [-0.7, 0.1, 0.2]], np.float32)
    turbidity = np.array([2, 5, 9], np.float32)
    session = ort.InferenceSession(str(out), providers=["CPUExecutionProvider"])
    (got,) = session.run(["image"], {"maps": maps, "sun": sun, "turbidity": turbidity})
    want = Renderer.from_checkpoint(trained, "cpu").render(maps, sun, turbidity)
    assert got.shape == want.shape and np.abs(got - want).max() < 1e-4

    option = next(p for p in trainer_main.commands["export"].params if p.name == "opset")
    assert (option.type.min, option.type.max) == (export.MIN_OPSET, export.OPSET)
    r = CliRunner().invoke(trainer_main, [*args[:-1], "10"])
    assert r.exit_code == 2 and "Invalid value for '--opset': 10 is not in the range" in r.output
    with pytest.raises(ValueError, match="opset 19 is not offered"):
        export.save_onnx(torch.nn.Identity(), {"x": torch.zeros(1)}, "y", out, opset=19)


def test_render_takes_an_exported_model_and_draws_what_its_checkpoint_draws(
    tiny_store, trained, tmp_path
):
    """``trainer render --checkpoint ball.onnx`` runs the exported file in ONNX Runtime: a
    stored sample, a new material (mapped with the layout beside the model) and a sweep come
    out as the checkpoint's pictures."""
    from render_jobs.specs import Sun
    from trainer.rendering.base import render_under
    from trainer.rendering.export import export
    from trainer.rendering.load import load_renderer
    from trainer.rendering.onnx_renderer import OnnxRenderer

    model = tmp_path / "ball.onnx"
    export(Renderer.from_checkpoint(trained, "cpu"), model)
    for what in (["--store", tiny_store.url, "--sample", "7"], ["--material", "procedural"]):
        pictures = []
        for source in (trained, model):
            out = tmp_path / f"{len(pictures)}.png"
            r = CliRunner().invoke(
                trainer_main, ["render", "--checkpoint", str(source), *what, "-o", str(out)]
            )
            assert r.exit_code == 0, r.output
            pictures.append(np.asarray(Image.open(out), np.int16))
        assert pictures[0].shape == (64, 64, 3) and pictures[0].std() > 1
        assert np.abs(pictures[0] - pictures[1]).max() <= 1, what  # 8-bit rounding at most

    onnx, torch_r = load_renderer(model), load_renderer(trained, "cpu")
    assert isinstance(onnx, OnnxRenderer) and (onnx.runtime, torch_r.runtime) == (
        "ONNX Runtime", "torch",
    )  # fmt: skip
    assert onnx.step == torch_r.step == checkpoint.load(trained)["step"]
    assert onnx.config == torch_r.config and onnx.tonemap == torch_r.tonemap
    maps = tiny_store.packed_maps(2)
    lights = [tiny_store.light(i) for i in range(5)]
    suns = [Sun(tuple(float(c) for c in d), float(t)) for d, t in lights]
    got = np.stack(list(render_under(onnx, maps, suns, batch=2)))
    want = np.stack(list(render_under(torch_r, maps, suns, batch=2)))
    assert got.shape == (5, 3, 64, 64) and np.abs(got - want).max() < 1e-4
    with pytest.raises(ValueError, match=r"maps have shape \(1, 10, 32, 32\), the model takes"):
        onnx.render_batch(torch.zeros(1, 11, 32, 32, dtype=torch.uint8), torch.zeros(1, 4))
    with pytest.raises(ValueError, match=r"maps are torch.float32 \(1, 11, 64, 64\), expected"):
        onnx.render_batch(torch.zeros(1, 11, 64, 64), torch.zeros(1, 4))


def test_an_exported_model_that_cannot_be_run_is_named_in_one_line(tiny_store, trained, tmp_path):
    import onnx
    from onnx import TensorProto, helper

    from trainer.rendering.export import export

    model = tmp_path / "ball.onnx"
    export(Renderer.from_checkpoint(trained, "cpu"), model)
    (tmp_path / "junk.onnx").write_bytes(b"not a model")
    x = helper.make_tensor_value_info("x", TensorProto.FLOAT, [1])
    y = helper.make_tensor_value_info("y", TensorProto.FLOAT, [1])
    graph = helper.make_graph([helper.make_node("Relu", ["x"], ["y"])], "relu", [x], [y])
    onnx.save(helper.make_model(graph), str(tmp_path / "other.onnx"))
    edited = onnx.load(str(model))
    next(p for p in edited.metadata_props if p.key == "shaderball.tonemap").value = "{oops"
    onnx.save(edited, str(tmp_path / "edited.onnx"))
    bare = tmp_path / "bare" / "ball.onnx"  # no screen UV layout beside it
    bare.parent.mkdir()
    bare.write_bytes(model.read_bytes())
    stored = ["--store", tiny_store.url, "--sample", "1", "-o", str(tmp_path / "x.png")]
    new = ["--material", "procedural", "-o", str(tmp_path / "x.png")]
    for source, args, says in [
        (tmp_path / "gone.onnx", stored, "gone.onnx: no such model"),
        (tmp_path / "junk.onnx", stored, "junk.onnx: not a model ONNX Runtime can load ("),
        (tmp_path / "other.onnx", stored, "other.onnx: not a model trainer export wrote (it"),
        (tmp_path / "edited.onnx", stored, "edited.onnx: its shaderball metadata is unreadable"),
        (model, [*stored, "--device", "cuda"], "ball.onnx: an .onnx model runs on the CPU here"),
        (bare, new, "no screen UV layout beside the model (ball.screen_uv.npz): pass --store"),
    ]:
        assert says in one_line_error(["render", "--checkpoint", str(source), *args])
    assert not (tmp_path / "x.png").exists()
    msg = one_line_error(["export", "-o", str(tmp_path / "again.onnx"), "--checkpoint", str(model)])
    assert "ball.onnx: an exported model, which trainer render, viewer and eval take" in msg
    assert not (tmp_path / "again.onnx").exists()


def test_eval_scores_an_exported_model_as_its_checkpoint(tiny_store, trained, tmp_path):
    """``trainer eval --checkpoint ball.onnx`` scores the file in ONNX Runtime on its run's
    held-out materials (named in its metadata) and on ``--on`` stores, with the checkpoint's
    figures. A model exported ``--no-catalog`` names no stores: its held-out split is refused
    in one line, writing nothing, and ``--on`` says it could not check the stores."""
    import onnx

    from trainer.rendering.export import export

    model = tmp_path / "ball.onnx"
    export(Renderer.from_checkpoint(trained, "cpu"), model)
    layout = Layout(num_materials=2, suns_per_material=2, resolution=64, shard_size=4)
    other = create_store(str(tmp_path / "other.zarr"), layout, {})
    write_shard(other, 0, synthetic_payload(layout, 0))
    for on in ([], ["--on", other.url]):
        results = []
        for source in (trained, model):
            grid = tmp_path / f"{source.name}.png"
            r = CliRunner().invoke(trainer_main, ["eval", "--checkpoint", str(source), *on,
                                                  "--json", "--grid", str(grid)])  # fmt: skip
            assert r.exit_code == 0, r.output
            results.append(json.loads(r.output[r.output.index("{") :]))
            assert Image.open(grid).size[0] == 3 * 256
        ours, theirs = results
        assert (ours["runtime"], theirs["runtime"]) == ("torch", "ONNX Runtime")
        assert ours["checkpoint_step"] == theirs["checkpoint_step"] == 54
        assert ours["samples"] == theirs["samples"] > 0
        assert theirs["on_checked_against_run"] is (True if on else None)
        for kind in ("overall", *ours["by_kind"]):
            a = ours if kind == "overall" else ours["by_kind"]
            b = theirs if kind == "overall" else theirs["by_kind"]
            for metric in ("psnr", "ssim", "flip"):
                assert a[kind][metric] == pytest.approx(b[kind][metric], abs=2e-3), (kind, metric)
    r = CliRunner().invoke(trainer_main, ["eval", "--checkpoint", str(model)])
    assert r.exit_code == 0 and "step 54 in ONNX Runtime: " in r.output, r.output
    bare = tmp_path / "share" / "bare.onnx"
    r = CliRunner().invoke(
        trainer_main, ["export", "--checkpoint", str(trained), "--no-catalog", "-o", str(bare)]
    )
    assert r.exit_code == 0, r.output
    keys = {p.key for p in onnx.load(str(bare)).metadata_props}
    assert "shaderball.model_config" in keys and "shaderball.catalog" not in keys
    assert tiny_store.url in model.read_bytes().decode("latin-1")
    assert tiny_store.url not in bare.read_bytes().decode("latin-1")  # no address in the file
    grid = tmp_path / "bare.png"
    msg = one_line_error(["eval", "--checkpoint", str(bare), "--grid", str(grid)])
    assert "bare.onnx: the model names no stores of its run (exported --no-catalog)" in msg
    moved = one_line_error(["eval", "--checkpoint", str(bare), "--store", "x", "--on", other.url])
    assert "bare.onnx: --store: the model names no stores of its run" in moved
    assert not grid.exists()
    r = CliRunner().invoke(trainer_main, ["eval", "--checkpoint", str(bare), "--on", other.url,
                                          "--json"])  # fmt: skip
    assert r.exit_code == 0, r.output
    assert "the --on stores were not checked for materials it trained on" in r.output
    scored = json.loads(r.output[r.output.index("{") :])
    assert scored["on_checked_against_run"] is False and scored["overall"]["n"] == 4


@pytest.mark.filterwarnings("ignore:This DataLoader will create")  # 3 > 2 cores
@pytest.mark.parametrize("workers", [0, 2, 3])
def test_one_iteration_reads_across_epochs_in_the_planned_order(tiny_store, workers):
    """The trainer reads all its epochs in one iteration (no restart at epoch ends): from a
    mid-epoch position, the batches are the pure plan of each epoch in turn, tagged with it,
    whatever the worker count (3 workers do not divide the first epoch's 2 batches)."""
    split = Catalog.snapshot([tiny_store.url], 0, 0.0, None).split("train")
    stream = ShardStream(split, batch=3, seed=0, buffer=256, world=2, rank=1, epochs=3)
    stream.set_position(1, 12)
    want = [(e, b.tolist()) for e in (1, 2) for b in stream.batches(e, 12 if e == 1 else 0)]
    got = [(b["epoch"], b["id"].tolist()) for b in loader(stream, workers)]  # the trainer's
    assert got == want and len(want) == 2 + 4


def test_held_out_scores_are_evenly_spaced_and_change_nothing_trained(tiny_store, tmp_path):
    split = Catalog.snapshot([tiny_store.url], 0, 0.5, None).split("test")
    n = len(split)
    assert list(Validator(split, 3).ids) == [0, round((n - 1) / 2), n - 1]
    assert list(Validator(split, 99).ids) == list(range(n)) and not len(Validator(split, 0))
    # scoring every step (eval mode, then back), or averaging the weights, leaves the
    # training where it was
    params = []
    for name, every, count, ema in (("scored", 1, 64, 0), ("unscored", 0, 0, 0),
                                    ("averaged", 1, 64, 0.9)):  # fmt: skip
        cfg = config(tiny_store, tmp_path / name, max_steps=4, val_every=every, val_samples=count,
                     ema_decay=ema)  # fmt: skip
        train(cfg)
        trained = Renderer.from_checkpoint(tmp_path / name, weights="trained")
        params.append(trained.model.state_dict())
        if name == "scored":  # resumed for 2 steps more: its first score is against the best
            train(dataclasses.replace(cfg, resume=True, max_steps=6))  # of the first process
    scored = [json.loads(x) for x in (tmp_path / "scored" / "val.jsonl").read_text().splitlines()]
    assert len(scored) == 6
    # each score: its materials (an interval needs 5), and after the first its PSNR less the
    # best before it, on the same samples
    v = Validator(split, 64)
    suns = tiny_store.layout.suns_per_material
    assert [tuple(g) for g in v.groups] == [(0, int(k) // suns) for _, k in split.refs[v.ids]]
    ran = Catalog.from_dict(checkpoint.load(tmp_path / "scored")["catalog"]).split("test")
    materials = len({tuple(g) for g in Validator(ran, 64).groups})
    assert all(x["materials"] == materials for x in scored)
    assert all((x["psnr_low"] is None) == (materials < 5) for x in scored)
    assert "vs_best" not in scored[0]
    wide = Validator(Catalog.snapshot([tiny_store.url], 0, 0.75, None).split("test"), 64)
    net = Renderer.from_checkpoint(tmp_path / "scored", device="cpu")
    got, _, each = wide.score(net.model, net.config.roughness_channels, net.tonemap)
    assert got["materials"] >= 5 and got["psnr_low"] < got["psnr"] < got["psnr_high"]
    assert wide.against(each, each) == {"mean": 0.0, "low": 0.0, "high": 0.0}
    for i, x in enumerate(scored[1:], 1):
        best = max(scored[:i], key=lambda y: y["psnr"])
        assert x["vs_best"]["step"] == best["step"]
        assert x["vs_best"]["mean"] == pytest.approx(x["psnr"] - best["psnr"], abs=2e-4)
    assert not (tmp_path / "unscored" / "val.jsonl").exists()
    assert all(torch.equal(params[0][k], p[k]) for p in params[1:] for k in params[0])
    # the averaged run's checkpoints render, and its scores measure, the average
    run = tmp_path / "averaged"
    val = [json.loads(line) for line in (run / "val.jsonl").read_text().splitlines()]
    scores = {w: evaluate(run, weights=w, device="cpu") for w in ("auto", "trained")}
    assert scores["auto"]["weights"] == "average" and scores["trained"]["weights"] == "trained"
    assert val[-1]["psnr"] == pytest.approx(scores["auto"]["overall"]["psnr"], abs=2e-3)
    assert scores["auto"]["overall"]["psnr"] != scores["trained"]["overall"]["psnr"]
    # ... and score the trained weights beside it, on the same samples
    assert val[-1]["trained_psnr"] == pytest.approx(scores["trained"]["overall"]["psnr"], abs=2e-3)
    assert val[-1]["trained_ssim"] == pytest.approx(scores["trained"]["overall"]["ssim"], abs=1e-4)
    assert len(val) == 4 and all(
        "trained_psnr" not in json.loads(x)
        for x in (tmp_path / "scored" / "val.jsonl").read_text().splitlines()
    )
    assert checkpoint.load(run)["ema"]["updates"] == 4
    assert evaluate(tmp_path / "scored", device="cpu")["weights"] == "trained"
    with pytest.raises(checkpoint.CheckpointError, match="scored.*kept no average"):
        evaluate(tmp_path / "scored", weights="average", device="cpu")


def test_torchrun_two_ranks_stay_identical_and_read_disjoint_samples(tiny_store, tmp_path):
    out = tmp_path / "ddp"
    cmd = [sys.executable, "-m", "trainer.cli", "launch", "--nproc-per-node", "2"]
    cmd += argv(tiny_store, out, epochs=2, batch_size=4, workers=2, log_samples=True)
    cmd += ["--val-every", "2", "--val-samples", "4"]
    r = run_group(cmd, timeout=300)
    assert r.returncode == 0, r.stderr[-3000:]
    assert "--standalone" in r.stderr and "done: " in r.stdout
    catalog = Catalog.from_dict(checkpoint.load(out)["catalog"])
    split = catalog.split("train")
    # rank 0 alone scored, every 2 steps and at each epoch's end (3 steps an epoch here)
    per_epoch = steps_left(len(split), 2, 4)
    val = [json.loads(line) for line in (out / "val.jsonl").read_text().splitlines()]
    ends = {per_epoch * e for e in (1, 2)}
    assert [x["step"] for x in val] == sorted(set(range(2, 2 * per_epoch + 1, 2)) | ends)
    assert {x["samples"] for x in val} == {4} and "held-out PSNR" in r.stdout
    best = max(val, key=lambda x: x["psnr"])  # a mid-epoch best writes its own checkpoint
    assert checkpoint.load(out / "checkpoints" / "best.pt")["step"] == best["step"]
    lines = [sample_lines(out, rank) for rank in range(2)]
    assert lines[0][-1].startswith("params ") and lines[0][-1] == lines[1][-1]
    for epoch in range(2):
        per_rank = []
        for rank in range(2):
            got = [ln.split()[2] for ln in lines[rank][:-1] if ln.split()[0] == str(epoch)]
            stream = ShardStream(split, batch=4, seed=0, buffer=256, world=2, rank=rank)
            stream.set_position(epoch, 0)
            assert got == [",".join(map(str, b)) for b in stream.batches()]  # the pure plan
            per_rank.append({int(i) for g in got for i in g.split(",")})
        assert not per_rank[0] & per_rank[1]
        assert per_rank[0] | per_rank[1] == set(range(len(split)))


def test_killed_run_resumes_with_exactly_the_remaining_order(tiny_store, tmp_path):
    ref = tmp_path / "ref"
    kw = {"epochs": 3, "log_samples": True, "checkpoint_every": 3, "lr_schedule": "cosine",
          "warmup_steps": 2, "ema_decay": 0.95}  # fmt: skip
    train(config(tiny_store, ref, **kw))
    full = sample_lines(ref)[:-1]

    run = tmp_path / "killed"
    cmd = [sys.executable, "-m", "trainer.cli", "train", *argv(tiny_store, run, **kw)]
    proc = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    target = checkpoint.folder(run) / "step-00000006.pt"
    deadline = time.monotonic() + 120
    while not target.exists() and proc.poll() is None and time.monotonic() < deadline:
        time.sleep(0.01)
    os.kill(proc.pid, signal.SIGKILL)
    assert proc.wait() == -signal.SIGKILL  # killed mid-run, not finished
    state = checkpoint.load(run)
    step = state["step"]
    assert 6 <= step < len(full)
    seen = len(sample_lines(run))

    train(config(tiny_store, run, **kw, resume=True))
    resumed = sample_lines(run)[seen:-1]
    assert resumed == full[step:]  # same steps, same epochs, same samples, same order
    a, b = checkpoint.load(ref), checkpoint.load(run)
    assert a["step"] == b["step"] and a["epoch"] == b["epoch"]
    assert sample_lines(ref)[-1] == sample_lines(run)[-1]  # the same weights (same rates)
    assert a["best"] is not None and b["best"] == a["best"]  # the best score survives a resume
    assert a["ema"]["updates"] == b["ema"]["updates"] == a["step"]  # and the average, exactly
    assert all(torch.equal(a["ema"]["weights"][k], b["ema"]["weights"][k]) for k in a["model"])
    assert checkpoint.load(run / "checkpoints" / "best.pt")["step"] == a["best"]["step"]
    kept = runfiles.kept_lines([json.loads(x) for x in (run / runfiles.LOG).open()])
    steps = [x["step"] for x in kept]  # the cut process's lines past the checkpoint are gone
    assert steps == sorted(set(steps)) and steps[-1] == a["step"]
    assert a["step"] - 2 < sum(x["steps"] for x in kept) <= a["step"]  # log_every 2


def test_a_cosine_resumed_for_more_epochs_goes_on_from_its_rate(tiny_store, tmp_path, capsys):
    """A run killed mid-cosine and resumed for twice the epochs goes on from the rate it had
    (no jump up) down to 0 at its new end; resumed again after that end, it is refused."""
    from trainer.training.schedule import lr_at

    run = tmp_path / "r"
    kw = {"lr_schedule": "cosine", "log_every": 1, "checkpoint_every": 2, "keep": 100}
    train(config(tiny_store, run, epochs=2, **kw))
    total = checkpoint.load(run)["schedule"]["total"]
    assert total > 6 and checkpoint.load(run)["schedule"]["knee"] == [0, 1.0]
    for p in checkpoint.folder(run).glob("*.pt"):  # killed just after its step-4 checkpoint
        if p.name == "best.pt" or int(p.stem.split("-")[1]) > 4:
            p.unlink()
    rates = {ln["step"]: ln["lr"] for ln in map(json.loads, (run / "log.jsonl").open())}
    capsys.readouterr()
    train(config(tiny_store, run, epochs=4, resume=True, **kw))
    knee = (4, lr_at(4, 1.0, "cosine", total))
    said = f"the run is {2 * total} steps long, not {total}: the cosine rate goes on from "
    assert (
        f"{said}{1e-3 * knee[1]:.3g} at step 4 to 0 at step {2 * total}" in capsys.readouterr().out
    )
    lines = [json.loads(ln) for ln in (run / "log.jsonl").read_text().splitlines()]
    resumed = {ln["step"]: ln["lr"] for ln in lines[len(rates) :]}
    assert sorted(resumed) == list(range(5, 2 * total + 1))  # every step, logged once
    for step, rate in resumed.items():  # the rate a step used: that of the step before
        assert rate == pytest.approx(lr_at(step - 1, 1e-3, "cosine", 2 * total, 0, knee), rel=1e-5)
    assert resumed[5] == rates[5] < lr_at(4, 1e-3, "cosine", 2 * total)  # on from there, no jump
    assert resumed[6] > rates[6]  # and down more slowly
    assert checkpoint.load(run)["schedule"] == {
        "schedule": "cosine", "total": 2 * total, "knee": [4, pytest.approx(knee[1])],
    }  # fmt: skip
    with pytest.raises(RunError, match=f"ended its cosine rate at step {2 * total}: more steps"):
        train(config(tiny_store, run, epochs=5, resume=True, **kw))


def test_a_resumed_run_keeps_its_network_and_says_where_it_goes_on_otherwise(
    tiny_store, tmp_path, capsys
):
    """Resumed with other network options (or after the recipe's defaults changed), a run
    goes on with the network of its checkpoint, and its checkpoints say so; the start lines
    name the network kept and a batch other than its own."""
    run = tmp_path / "r"
    kw = {"lr_schedule": "constant", "recipe": "shaderball", "width": 8}
    train(config(tiny_store, run, max_steps=2, inputs="light", batch_size=4, **kw))
    capsys.readouterr()
    train(config(tiny_store, run, max_steps=4, resume=True, inputs="light,shadow", **kw))
    out = capsys.readouterr().out
    kept = checkpoint.load(run)
    assert kept["step"] == 4 and kept["model_config"]["inputs"] == ["light"]
    assert kept["config"]["inputs"] == ["light"] and kept["config"]["batch_size"] == 2
    assert "its network goes on as it was trained (--inputs light)" in out
    assert "resuming at batch 2; " in out and "trained at 4 (--batch-size 4 goes on" in out


def test_weight_decay_shrinks_every_weight_apart_from_the_step_and_a_resume_takes_its_own(
    tiny_store, tmp_path
):
    """``--weight-decay D`` is decoupled (AdamW): after one step at rate r from the same
    start, a run with it differs from one without by exactly ``r x D x`` the initial weights;
    a run resumed with another decay steps with that one."""
    kw = {"lr": 1e-3, "lr_schedule": "constant", "max_steps": 1, "workers": 0}
    train(config(tiny_store, tmp_path / "plain", **kw))
    train(config(tiny_store, tmp_path / "decayed", weight_decay=100.0, **kw))
    plain, decayed = checkpoint.load(tmp_path / "plain"), checkpoint.load(tmp_path / "decayed")
    torch.manual_seed(0)  # the runs' initial weights
    fresh = NeuralRenderer(ModelConfig(**plain["model_config"]))
    start = fresh.state_dict()
    # p·(1 - r·D) - update against p - update: the update is the same
    for k, _ in fresh.named_parameters():
        shrunk = plain["model"][k] - decayed["model"][k]
        assert torch.allclose(shrunk, 1e-3 * 100.0 * start[k], rtol=1e-4, atol=1e-6), k
    assert decayed["optimizer"]["param_groups"][0]["weight_decay"] == 100.0
    train(config(tiny_store, tmp_path / "decayed", weight_decay=0.5, resume=True,
                 **(kw | {"max_steps": 2})))  # fmt: skip
    groups = checkpoint.load(tmp_path / "decayed")["optimizer"]["param_groups"]
    assert groups[0]["weight_decay"] == 0.5
    bad = ["train", "--store", tiny_store.url, "--out", str(tmp_path / "bad")]
    r = CliRunner().invoke(trainer_main, [*bad, "--weight-decay", "-1"])
    assert r.exit_code != 0 and "--weight-decay must be at least 0, not -1" in r.output
    assert not (tmp_path / "bad").exists()


def test_a_bf16_run_on_the_cpu_autocasts_its_steps_and_keeps_fp32_weights(
    tiny_store, tmp_path, capsys
):
    """``--precision bf16`` on the CPU: the run says so as it starts, its steps take another
    path than fp32's from the same start (so autocast ran), and its checkpoint names the
    precision and keeps fp32 weights and optimizer state, close to the fp32 run's."""
    kw = {"lr": 1e-3, "lr_schedule": "constant", "max_steps": 2, "workers": 0, "device": "cpu"}
    train(config(tiny_store, tmp_path / "fp32", precision="fp32", **kw))
    assert " on cpu in fp32, " in capsys.readouterr().out
    train(config(tiny_store, tmp_path / "bf16", precision="bf16", **kw))
    assert " on cpu in bf16, " in capsys.readouterr().out
    full, half = checkpoint.load(tmp_path / "fp32"), checkpoint.load(tmp_path / "bf16")
    assert (full["precision"], half["precision"]) == ("fp32", "bf16")
    weights = [k for k, v in half["model"].items() if v.is_floating_point()]
    assert all(half["model"][k].dtype == torch.float32 for k in weights)
    moments = [v["exp_avg"] for v in half["optimizer"]["state"].values()]
    assert moments and all(m.dtype == torch.float32 for m in moments)
    apart = max((half["model"][k] - full["model"][k]).abs().max().item() for k in weights)
    assert 0 < apart < 0.05


def test_a_run_fine_tunes_another_runs_network_on_more_stores(tiny_store, tmp_path, capsys):
    """``--init``: the network (the average's weights, shape, here with two convolutions a
    decoder level, tonemap) of another run, a fresh optimizer at step 0, the first run's
    held-out materials still held out; a run folder with checkpoints resumes instead; a store
    of another resolution and network options given beside it are refused."""
    first = tmp_path / "first"
    train(config(tiny_store, first, width=8, exposure=0.5, ema_decay=0.9, max_steps=2,
                 decoder_convs=2))  # fmt: skip
    was = checkpoint.load(first)
    layout = Layout(num_materials=2, suns_per_material=2, resolution=64, shard_size=4)
    more = create_store(str(tmp_path / "more.zarr"), layout, {})
    write_shard(more, 0, synthetic_payload(layout, 0))
    run = tmp_path / "tuned"
    cfg = TrainConfig(**{**BASE, "store": (tiny_store.url, more.url), "out": str(run),
                         "init": str(first), "lr": 1e-30, "max_steps": 1})  # fmt: skip
    train(cfg)
    now = checkpoint.load(run)
    assert now["step"] == 1 and now["best"]["step"] == 1 and "ema" not in now
    assert now["model_config"] == was["model_config"] and now["tonemap"] == was["tonemap"]
    average = checkpoint.weights(was)  # a step at rate 1e-30 moves no weight measurably
    assert not all(torch.equal(average[k], was["model"][k]) for k in average)
    params = [k for k in average if "running_" not in k and "batches" not in k]  # not BN stats
    assert all(torch.allclose(now["model"][k], average[k], rtol=0, atol=1e-20) for k in params)
    assert now["catalog"]["heldout"][0] == was["catalog"]["heldout"][0]
    assert len(now["catalog"]["heldout"][1]) == 1  # a quarter of the new store's 2, at least 1
    said = json.loads((run / "config.json").read_text())
    assert (said["width"], said["exposure"], said["init"]) == (8, 0.5, str(first))
    assert said["decoder_convs"] == now["model_config"]["decoder_convs"] == 2
    assert f"fine-tuning the network of {first}" in capsys.readouterr().out
    train(dataclasses.replace(cfg, resume=True, max_steps=2))
    assert checkpoint.load(run)["step"] == 2  # resumed, not started again from --init
    assert "only starts a run" in capsys.readouterr().out

    big = Layout(num_materials=2, suns_per_material=2, resolution=128, shard_size=4)
    other = create_store(str(tmp_path / "big.zarr"), big, {})
    write_shard(other, 0, synthetic_payload(big, 0))
    with pytest.raises(RunError, match=f"{first} renders 64², the stores hold 128²"):
        train(config(SimpleNamespace(url=other.url), tmp_path / "big", init=str(first)))
    assert not (tmp_path / "big").exists()
    start = ["train", "--store", tiny_store.url, "--out", str(tmp_path / "x"), "--init"]
    r = CliRunner().invoke(trainer_main, [*start, str(first), "--no-skips"])
    assert r.exit_code == 2 and "--skips: a run started from --init takes its network" in r.output
    (tmp_path / "ball.onnx").write_bytes(b"onnx")
    onnx = one_line_error([*start, str(tmp_path / "ball.onnx")])
    assert "ball.onnx: an exported model" in onnx
    ghost = {**was, "catalog": {**was["catalog"], "urls": [str(tmp_path / "gone.zarr")]}}
    catalog = Catalog.from_dict(was["catalog"])  # names its materials: no store is read
    kept = (set(catalog.trained_sources), set(catalog.held_sources))
    assert train_module._kept(cfg, ghost) == kept and len(kept[1]) == 2
    assert kept == catalog.material_sources([tiny_store])  # as the store says
    capsys.readouterr()
    old = {**ghost, "catalog": {**ghost["catalog"], "trained_sources": None, "held_sources": None}}
    assert train_module._kept(cfg, old) is None  # kept without them, its stores gone: said
    assert "its stores cannot be read" in capsys.readouterr().out


def test_a_material_in_two_stores_is_held_out_in_both_or_neither(tiny_store, tmp_path, capsys):
    """``again`` holds two of the tiny store's materials (their ``source_id``), rendered again."""
    layout = Layout(num_materials=2, suns_per_material=2, resolution=64, shard_size=4)
    again = create_store(str(tmp_path / "again.zarr"), layout, {})
    payload = synthetic_payload(layout, 0)
    records = tiny_store.materials()
    for m, rec in enumerate(payload.materials):
        rec["source_id"] = records[m]["source_id"]
    write_shard(again, 0, payload)
    run = tmp_path / "run"
    stores = (tiny_store.url, again.url)
    train(TrainConfig(**{**BASE, "store": stores, "out": str(run), "max_steps": 1,
                         "holdout_fraction": 0.5}))  # fmt: skip
    held = checkpoint.load(run)["catalog"]["heldout"]
    assert held[1] == [m for m in (0, 1) if m in held[0]]
    assert len(held[0]) == 4  # half of the 8 distinct materials
    assert "2 material(s) are in more than one store" in capsys.readouterr().out
    with pytest.raises(ValueError, match="again.zarr is given twice"):
        TrainConfig(**{**BASE, "store": (*stores, again.url), "out": str(run)})


def test_perceptual_loss_and_divergence(tiny_store, tmp_path):
    weights = vgg_weights_file(tmp_path / "vgg16.pth")
    out = tmp_path / "vgg"
    summary = train(config(tiny_store, out, loss="l1+vgg", vgg_weights=str(weights), max_steps=2))
    assert summary["steps"] == 2 and checkpoint.load(out)["config"]["loss"] == "l1+vgg"
    good = checkpoint.latest(out)
    with pytest.raises(
        TrainingDiverged, match=r"NaN/Inf by step \d+; stopped. Last good checkpoint"
    ):
        train(
            config(
                tiny_store, out, loss="l1+vgg", vgg_weights=str(weights), lr=1e30, resume=True,
                checkpoint_every=1, log_every=100, keep=10,
            )
        )  # fmt: skip
    kept = checkpoint.listing(out)
    assert good in kept and len(kept) <= 3  # at most one step on before the NaN showed
    for path in kept:  # nothing written from NaN/Inf weights
        assert all(torch.isfinite(v).all() for v in checkpoint.load(path)["model"].values())


def test_the_flip_loss_trains_and_is_kept_with_the_run(tiny_store, tmp_path):
    out = tmp_path / "flip"
    summary = train(config(tiny_store, out, loss="l1+flip", max_steps=2))
    assert summary["steps"] == 2 and checkpoint.load(out)["config"]["loss"] == "l1+flip"
    logged = [json.loads(x) for x in (out / "log.jsonl").read_text().splitlines()]
    assert [x["loss"] for x in logged if "loss" in x] and all(
        0 < x["loss"] < 1 for x in logged if "loss" in x
    )


def one_line_error(args: list[str], env: dict | None = None) -> str:
    r = CliRunner().invoke(trainer_main, args, env=env)
    assert r.exit_code == 1, r.output
    lines = r.output.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("Error: "), r.output
    return lines[0]


def test_bad_inputs_get_one_line_errors_and_leave_nothing(tiny_store, tmp_path):
    run = tmp_path / "run"
    base = ["train", "--loss", "l1", "--out", str(run)]

    (tmp_path / "plain.zarr").mkdir()
    (tmp_path / "plain.zarr" / "zarr.json").write_text(json.dumps({"node_type": "group"}))
    msg = one_line_error([*base, "--store", str(tmp_path / "plain.zarr")])
    assert "plain.zarr: a zarr store, but not a shaderball shard store" in msg

    newer = tmp_path / "newer.zarr"
    create_store(str(newer), Layout(1, 1, 16, 1), {})
    meta = json.loads((newer / "zarr.json").read_text())
    meta["attributes"]["shaderball"]["schema_version"] = 99
    (newer / "zarr.json").write_text(json.dumps(meta))
    assert "unknown schema version 99" in one_line_error([*base, "--store", str(newer)])

    empty = create_store(str(tmp_path / "empty.zarr"), Layout(2, 1, 16, 1), {})
    assert "no committed samples" in one_line_error([*base, "--store", empty.url])

    odd_layout = Layout(2, 1, 40, 1)
    odd = create_store(str(tmp_path / "odd.zarr"), odd_layout, {})
    for shard in range(2):
        write_shard(odd, shard, synthetic_payload(odd_layout, shard))
    assert "resolution 40 is not a multiple of 16" in one_line_error([*base, "--store", odd.url])
    for option, value in [("--width", "0"), ("--seed", "-1"), ("--roughness-channels", "2"),
                          ("--perceptual-weight", "-1"), ("--epochs", "0"),
                          ("--val-every", "-1"), ("--val-samples", "-2"),
                          ("--warmup-steps", "-1"), ("--ema-decay", "1.0"),
                          ("--holdout-seed", "-1")]:  # fmt: skip
        msg = one_line_error([*base, "--store", tiny_store.url, option, value])
        assert re.fullmatch(rf"Error: {option} must be .+, not {value}(\.0)?", msg), msg

    env = {"TORCH_HOME": str(tmp_path / "torch-home")}
    paper = ["--recipe", "paper"]  # its loss, L1 + VGG16, needs the ImageNet weights
    msg = one_line_error(["train", *paper, "--out", str(run), "--store", tiny_store.url], env=env)
    assert "needs ImageNet VGG16 weights" in msg and "--vgg-weights FILE" in msg
    nope = tmp_path / "nope.zarr"  # the store typed wrong is named before the missing weights
    r = CliRunner().invoke(
        trainer_main, ["launch", *paper, "--out", str(run), "--store", str(nope)], env=env
    )
    assert (
        r.exit_code == 1
        and r.output.splitlines()[-1] == f"Error: {nope}: not a shard store (no zarr.json)"
    )
    assert "missing.pth does not exist" in one_line_error(
        [
            *base[:1],
            *paper,
            "--vgg-weights",
            str(tmp_path / "missing.pth"),
            "--store",
            tiny_store.url,
        ]
    )
    weights = vgg_weights_file(tmp_path / "vgg16.pth")  # given, but the loss reads none
    msg = one_line_error([*base, *paper, "--vgg-weights", str(weights), "--store", tiny_store.url])
    assert msg == "Error: --vgg-weights is read only by --loss l1+vgg, not by l1", msg
    assert "no store given" in one_line_error(base)
    assert not run.exists()  # nothing half written

    assert "no checkpoints" in one_line_error(["eval", "--checkpoint", str(tmp_path)])
    # files that are not checkpoints: one line each, without torch's advice to load unsafely
    (tmp_path / "text.pt").write_text("not a checkpoint\n")
    torch.save({"x": SimpleNamespace()}, tmp_path / "object.pt")
    torch.save({"step": 3}, tmp_path / "dict.pt")
    for name, reason in [
        ("text.pt", "not a readable checkpoint (not a file torch.save writes)"),
        ("object.pt", "not a readable checkpoint (Unsupported global: GLOBAL types.Simple"),
        ("dict.pt", "not a shaderball checkpoint (no 'model')"),
    ]:
        line = one_line_error(["eval", "--checkpoint", str(tmp_path / name)])
        assert line.startswith(f"Error: {tmp_path / name}: {reason}") and "weights_only" not in line


@pytest.mark.skipif(torch.cuda.is_available(), reason="checks the refusal where CUDA is absent")
def test_cuda_asked_for_where_torch_sees_none_is_one_line(tiny_store, trained, tmp_path):
    """``--device cuda`` on a machine without CUDA, and ``trainer viewer --cuda-graph`` off
    CUDA, end in one line before any work: nothing trained, written or served."""
    nocuda = f"Error: --device cuda: this torch ({torch.__version__}) sees no CUDA device"
    run = tmp_path / "run"
    for cmd in ("train", "launch"):
        argv_ = [cmd, "--loss", "l1", "--store", tiny_store.url, "--out", str(run)]
        assert one_line_error([*argv_, "--device", "cuda"]) == nocuda
    assert not run.exists()
    png = tmp_path / "ball.png"
    render = ["render", "--checkpoint", str(trained), "--store", tiny_store.url, "--sample", "0",
              "-o", str(png)]  # fmt: skip
    for args in (["eval", "--checkpoint", str(trained)], render,
                 ["viewer", "--checkpoint", str(trained), "--store", tiny_store.url,
                  "--cuda-graph"]):  # fmt: skip
        assert one_line_error([*args, "--device", "cuda"]) == nocuda
    assert not png.exists()
    viewer = ["viewer", "--checkpoint", str(trained), "--cuda-graph"]
    assert one_line_error(viewer) == (
        "Error: --cuda-graph needs a CUDA device, and the network would run on cpu"
    )


def test_existing_run_needs_resume_and_eval_needs_a_holdout(tiny_store, tmp_path):
    out = tmp_path / "r"
    train(config(tiny_store, out, max_steps=1, holdout_fraction=0.0))
    assert not (out / "val.jsonl").exists()  # nothing held out, nothing scored
    msg = one_line_error(["train", "--loss", "l1", "--store", tiny_store.url, "--out", str(out)])
    assert "already holds checkpoints: pass --resume" in msg
    resume = ["train", "--loss", "l1", "--store", tiny_store.url, "--out", str(out), "--resume"]
    assert "trained with --seed 0, not 5" in one_line_error([*resume, "--seed", "5"])
    # the resumed run keeps its held-out draw, so another one is refused
    assert "trained with --holdout-fraction 0.0, not 0.02" in one_line_error(resume)
    same = [*resume, "--holdout-fraction", "0"]
    assert "trained with --holdout-seed 0, not 3" in one_line_error([*same, "--holdout-seed", "3"])
    assert "no held-out samples" in one_line_error(["eval", "--checkpoint", str(out)])


def test_runs_of_other_seeds_hold_out_the_same_materials(tiny_store, tmp_path):
    """``--seed`` changes the init and the shuffle, not the held-out draw, so a seed sweep's
    held-out scores compare; ``--holdout-seed`` draws others."""
    held, sets = {}, {}
    for name, kw in (("a", {}), ("b", {"seed": 1}), ("c", {"holdout_seed": 1})):
        run = tmp_path / name
        train(config(tiny_store, run, max_steps=1, holdout_fraction=0.5, val_every=1, **kw))
        held[name] = checkpoint.load(run)["catalog"]["heldout"]
        sets[name] = json.loads((run / "val.jsonl").read_text())["heldout_set"]
    assert held["a"] == held["b"] and held["a"] != held["c"]
    assert len(held["a"][0]) == len(held["c"][0]) == 4  # half of the 8 materials
    assert sets["a"] == sets["b"] != sets["c"]  # the scores name the samples they score


def test_a_run_names_its_store_absolutely_and_is_read_from_any_folder(
    tiny_store, tmp_path, monkeypatch
):
    """A store given relative to the folder training started in is recorded absolute: the
    run evaluates from another folder, and resumes with the same store named either way."""
    store = Path(tiny_store.url)
    monkeypatch.chdir(store.parent)
    cfg = TrainConfig(**{**BASE, "store": (store.name, "s3://b/d.zarr"), "out": "r"})
    assert cfg.store == (str(store), "s3://b/d.zarr")
    run = tmp_path / "run"
    relative = SimpleNamespace(url=store.name)
    train(config(relative, run, max_steps=1, holdout_fraction=0.3))
    assert json.loads((run / "config.json").read_text())["store"] == [str(store)]
    monkeypatch.chdir(tmp_path)
    r = CliRunner().invoke(trainer_main, ["eval", "--checkpoint", "run", "--json"])
    assert r.exit_code == 0, r.output
    gone = one_line_error(["eval", "--checkpoint", "run", "--store", "moved.zarr"])
    assert gone.endswith("moved.zarr: not a shard store (no zarr.json): the run's store is not "
                         "there; --store says where it is")  # fmt: skip
    monkeypatch.chdir(store.parent)
    train(config(relative, run, max_steps=2, holdout_fraction=0.3, resume=True))
    assert checkpoint.load(run)["step"] == 2


def test_eval_on_other_materials_refuses_the_runs_own(tiny_store, trained, tmp_path):
    """``--on`` evaluates every sample of a store of other materials; a store whose materials
    the run trained on is refused, and so is a run store that is not where ``--store`` says."""
    layout = Layout(num_materials=2, suns_per_material=2, resolution=64, shard_size=4)
    other = create_store(str(tmp_path / "other.zarr"), layout, {})
    write_shard(other, 0, synthetic_payload(layout, 0))
    r = CliRunner().invoke(trainer_main, ["eval", "--checkpoint", str(trained), "--json",
                                          "--on", other.url])  # fmt: skip
    assert r.exit_code == 0, r.output
    assert json.loads(r.output[r.output.index("{") :])["overall"]["n"] == 4
    own = one_line_error(["eval", "--checkpoint", str(trained), "--on", tiny_store.url])
    assert "of its materials were trained on" in own and own.startswith(f"Error: {tiny_store.url}")
    moved = ["--store", str(tmp_path / "moved.zarr"), "--on", other.url, "--json"]
    r = CliRunner().invoke(trainer_main, ["eval", "--checkpoint", str(trained), *moved])
    assert r.exit_code == 0, r.output  # the checkpoint names its materials: no store is read
    state = checkpoint.load(checkpoint.latest(trained))
    state["catalog"] |= {"trained_sources": None, "held_sources": None}  # as kept without them
    torch.save(state, tmp_path / "old.pt")
    old = ["eval", "--checkpoint", str(tmp_path / "old.pt"), *moved]
    assert "the run's store is not there" in one_line_error(old)
    small = create_store(str(tmp_path / "small.zarr"), Layout(2, 2, 32, 4), {})
    wrong = ["eval", "--checkpoint", str(trained), "--store"]
    for store, says in [
        (small.url, "small.zarr: 32², the run's stores are 64²: not the run's store"),
        (other.url, "other.zarr: 3 shard(s) the run read are not committed there (e.g. shard 1)"),
    ]:  # another store at --store is named, not read into a traceback
        assert says in one_line_error([*wrong, store]), store


def test_eval_compares_checkpoints_on_the_same_samples(tiny_store, trained, tmp_path):
    """Several --checkpoint are scored on the same samples as eval scores each alone, each
    against the first; runs that hold out other samples are refused."""
    early = sorted((trained / "checkpoints").glob("step-*.pt"))[0]
    models = [str(trained), str(early), str(trained)]
    kept = (trained / "eval.json").read_bytes() if (trained / "eval.json").exists() else None
    each = [x for m in models for x in ("--checkpoint", m)]
    r = CliRunner().invoke(trainer_main, ["eval", *each, "--grid", str(tmp_path / "cmp.png"),
                                          "--json"])  # fmt: skip
    assert r.exit_code == 0, r.output
    result = json.loads(r.output[r.output.index("{") :])
    alone = [evaluate(m, device="cpu", grid_count=0) for m in models[:2]]
    assert result["samples"] == alone[0]["samples"] == result["models"][0]["overall"]["n"]
    assert result["materials"] == len(checkpoint.load(trained)["catalog"]["heldout"][0])
    assert result["heldout_set"] == json.loads(
        (trained / "val.jsonl").read_text().splitlines()[-1])["heldout_set"]  # fmt: skip
    first, second, again = result["models"]
    for together, one in ((first, alone[0]), (second, alone[1])):
        assert together["overall"] == one["overall"] and together["by_kind"] == one["by_kind"]
    assert [m["checkpoint_step"] for m in result["models"]] == [
        54,
        checkpoint.load(early)["step"],
        54,
    ]
    assert [m["label"] for m in result["models"]] == [
        f"{trained} (trained)", str(early), f"{trained} (trained)"]  # fmt: skip
    d = second["vs_first"]["psnr"]
    assert d["mean"] == pytest.approx(
        second["overall"]["psnr"] - first["overall"]["psnr"], abs=2e-3
    )
    assert d["materials"] == 2 and d["low"] is None  # too few materials for an interval
    assert again["vs_first"]["psnr"]["mean"] == 0 and again["vs_first"]["flip"]["higher"] == 0
    # ground truth, three networks, three errors; nothing kept beside the run
    assert Image.open(tmp_path / "cmp.png").size == (7 * 256, 24 + 4 * 256)
    after = (trained / "eval.json").read_bytes() if (trained / "eval.json").exists() else None
    assert after == kept
    # every sample's scores, where it is, its material and its sun, for each model
    table = tmp_path / "out" / "samples.csv"
    r = CliRunner().invoke(trainer_main, ["eval", *each[:4], "--per-sample", str(table)])
    assert r.exit_code == 0 and f"each sample's scores: {table}" in r.output, r.output
    rows = list(csv.DictReader(table.open()))
    assert len(rows) == result["samples"] and list(rows[0])[-6:] == [
        "psnr_1", "ssim_1", "flip_1", "psnr_2", "ssim_2", "flip_2"]  # fmt: skip
    for i, model in ((1, first), (2, second)):
        mean = np.mean([float(x[f"psnr_{i}"]) for x in rows])
        assert mean == pytest.approx(model["overall"]["psnr"], abs=2e-3)
    kinds = {m: rec["kind"] for m, rec in tiny_store.materials().items()}
    for x in rows:
        sample, material = int(x["sample"]), int(x["material"])
        sun, turbidity = tiny_store.light(sample)
        assert x["store"] == tiny_store.url and x["kind"] == kinds[material]
        assert material == tiny_store.layout.material_of_sample(sample)
        assert float(x["turbidity"]) == pytest.approx(turbidity, rel=1e-5)
        assert np.sin(np.radians(float(x["sun_elevation_deg"]))) == pytest.approx(sun[2], abs=1e-3)
    alone = tmp_path / "alone.csv"
    r = CliRunner().invoke(trainer_main, ["eval", "--checkpoint", str(early), "--grid-count", "0",
                                          "--per-sample", str(alone)])  # fmt: skip
    assert r.exit_code == 0, r.output
    assert [x["psnr_2"] for x in rows] == [x["psnr_1"] for x in csv.DictReader(alone.open())]
    r = CliRunner().invoke(
        trainer_main, ["eval", *each[:2], "--per-sample", str(tmp_path / "s.txt")]
    )
    assert r.exit_code == 2 and "--per-sample: '" in r.output and "a .csv file" in r.output
    assert not (tmp_path / "s.txt").exists()
    # the table: each model, PSNR by kind, each against the first
    two = ["eval", "--checkpoint", str(trained), "--checkpoint", str(early)]
    r = CliRunner().invoke(trainer_main, [*two, "--grid-count", "0"])
    assert r.exit_code == 0, r.output
    assert f"{result['samples']} held-out samples of 2 materials" in r.output
    assert ", held out by 1), every model on the same ones" in r.output
    assert "PSNR dB by material kind" in r.output and "against 1: mean difference" in r.output
    assert "(no intervals: fewer than 5 materials)" in r.output
    assert f"{d['mean']:+.2f}" in r.output.split("against 1")[1]
    # on other stores, every model on all their samples
    layout = Layout(num_materials=2, suns_per_material=2, resolution=64, shard_size=4)
    other = create_store(str(tmp_path / "other.zarr"), layout, {})
    write_shard(other, 0, synthetic_payload(layout, 0))
    on = CliRunner().invoke(trainer_main, [*two, "--on", other.url, "--json"])
    assert on.exit_code == 0, on.output
    assert json.loads(on.output[on.output.index("{") :])["samples"] == 4
    # another held-out draw, another tonemap, and a count of --weights that matches nothing
    run = tmp_path / "other-draw"
    train(config(tiny_store, run, max_steps=1, holdout_seed=1))
    msg = one_line_error(["eval", "--checkpoint", str(trained), "--checkpoint", str(run)])
    assert msg.startswith(f"Error: {run}: trained on 2 of the 2 materials {trained} holds out")
    bright = tmp_path / "bright"  # the same held-out samples, brighter targets
    train(config(tiny_store, bright, max_steps=1, exposure=2.0))
    msg = one_line_error(["eval", "--checkpoint", str(trained), "--checkpoint", str(bright)])
    assert msg.startswith(f"Error: {bright}: trained against another tonemap than {trained}")
    r = CliRunner().invoke(
        trainer_main, ["eval", *each, "--weights", "auto", "--weights", "trained"]
    )
    assert r.exit_code == 2 and "--weights: given 2 times for 3 checkpoints" in r.output


def test_eval_compares_a_network_with_one_fine_tuned_from_it(tiny_store, trained, tmp_path):
    """A fine-tuned run holds out its first run's held-out materials and more: compared
    either way round, every model is scored on the first's held-out samples."""
    layout = Layout(num_materials=8, suns_per_material=2, resolution=64, shard_size=4)
    more = create_store(str(tmp_path / "more.zarr"), layout, {})
    for shard in range(layout.num_shards):
        write_shard(more, shard, synthetic_payload(layout, shard, seed=3))
    tuned = tmp_path / "tuned"
    train(TrainConfig(**{**BASE, "store": (tiny_store.url, more.url), "out": str(tuned),
                         "init": str(trained), "max_steps": 1}))  # fmt: skip
    alone = {str(m): evaluate(m, device="cpu", grid_count=0) for m in (trained, tuned)}
    for first, second in ((trained, tuned), (tuned, trained)):
        r = CliRunner().invoke(trainer_main, ["eval", "--checkpoint", str(first),
                                              "--checkpoint", str(second), "--json"])  # fmt: skip
        assert r.exit_code == 0, r.output
        result = json.loads(r.output[r.output.index("{") :])
        assert result["models"][0]["overall"] == alone[str(first)]["overall"]
        assert result["samples"] == alone[str(first)]["samples"]
    assert alone[str(tuned)]["samples"] > alone[str(trained)]["samples"]  # and more's held out
    exported = tmp_path / "bare.onnx"
    r = CliRunner().invoke(trainer_main, ["export", "--checkpoint", str(trained), "-o",
                                          str(exported), "--no-catalog"])  # fmt: skip
    assert r.exit_code == 0, r.output
    msg = one_line_error(["eval", "--checkpoint", str(tuned), "--checkpoint", str(exported)])
    assert msg.startswith(f"Error: {exported}: the model names no stores of its run")


def test_launch_commands():
    r = CliRunner().invoke(trainer_main, ["launch", "--dry-run", "--store", "s.zarr"])
    assert r.exit_code == 0 and "--standalone --nnodes 1 --nproc-per-node 1" in r.output
    args = ["launch", "--dry-run", "--nodes", "2", "--nproc-per-node", "8"]
    args += ["--rdzv-endpoint", "head:29400", "--store", "s3://b/d.zarr"]
    r = CliRunner().invoke(trainer_main, args)
    assert r.exit_code == 0, r.output
    assert "--rdzv-backend c10d --rdzv-endpoint head:29400 --rdzv-id shaderball " in r.output
    # c10d ranks the nodes itself (torchrun warns of a node rank there): one command for all
    others = [line for line in r.output.splitlines() if line.startswith("on each other node: ")]
    assert others == [
        "on each other node: trainer launch --nodes 2 --nproc-per-node 8 "
        "--rdzv-endpoint head:29400 --max-restarts 0 --store s3://b/d.zarr"
    ]
    assert "--node-rank" not in r.output
    assert "nodes need --rdzv-endpoint" in one_line_error(
        ["launch", "--nodes", "2", "--store", "s"]
    )
    for option, value, says in [
        ("--master-port", "99999", "99999 is not in the range 1<=x<=65535"),
        ("--max-restarts", "-1", "-1 is not in the range x>=0"),
    ]:
        r = CliRunner().invoke(trainer_main, ["launch", "--dry-run", "--store", "s", option, value])
        assert r.exit_code == 2 and f"Error: Invalid value for '{option}': {says}" in r.output


@pytest.mark.parametrize("flaky", [False, True], ids=["s3", "flaky-s3"])
def test_trains_from_an_s3_store(tiny_store, s3, tmp_path, flaky):
    """The loader streams shards from object storage (credentials and endpoint from the
    standard AWS environment variables, as on a cluster), also through a proxy that answers
    503 SlowDown or resets the connection on four reads, one in every 15, for more tries of
    each than s3fs makes (botocore's own retries off), so the faults reach this project's
    retry policy, with the same samples."""
    endpoint, opts = s3
    url = f"s3://shaderball/tiny-{flaky}.zarr"
    remote = create_store(url, tiny_store.layout, tiny_store.settings, storage_options=opts)
    for shard in tiny_store.committed_shards():
        write_shard(remote, shard, tiny_store.read_shard(shard))
    proxy = FlakyProxy.past_client_retries(endpoint, every=15, method="GET") if flaky else None
    with proxy or contextlib.nullcontext():
        env = {
            **os.environ,
            "AWS_ACCESS_KEY_ID": "test",
            "AWS_SECRET_ACCESS_KEY": "test",
            "AWS_ENDPOINT_URL": proxy.endpoint if proxy else endpoint,
            "AWS_DEFAULT_REGION": "us-east-1",
            "AWS_MAX_ATTEMPTS": "1",
            "AWS_RETRY_MODE": "standard",
        }
        out = tmp_path / "s3run"
        cmd = [sys.executable, "-m", "trainer.cli", "train"]
        cmd += argv(remote, out, max_steps=3, workers=2, log_samples=True)
        r = run_group(cmd, env=env, timeout=300)
    assert r.returncode == 0, r.stderr[-2000:]
    if proxy:
        assert proxy.faults["503"] and proxy.faults["reset"], proxy.faults
        assert "retry 1 in" in r.stderr  # each retry logged
    state = checkpoint.load(out)
    assert state["step"] == 3 and state["catalog"]["urls"] == [url]
    local = Catalog.from_dict({**state["catalog"], "urls": [tiny_store.url]})
    stream = ShardStream(local.split("train"), batch=2, seed=0, buffer=256)
    want = [",".join(map(str, b)) for b in stream.batches()[:3]]
    assert [ln.split()[2] for ln in sample_lines(out)[:-1]] == want


def test_torchrun_restart_resumes_from_the_last_checkpoint(tiny_store, tmp_path):
    """Rank 0 dies abruptly at step 5 of the first attempt; torchrun (--max-restarts 1)
    restarts both ranks, which resume from the step-4 checkpoint and finish the job."""
    out = tmp_path / "restart"
    cmd = [sys.executable, "-m", "trainer.cli", "launch", "--nproc-per-node", "2"]
    cmd += ["--max-restarts", "1"]
    cmd += argv(tiny_store, out, epochs=2, checkpoint_every=2, log_samples=True)
    env, tmp = private_tmp(tmp_path, {**os.environ, "SHADERBALL_TRAIN_CRASH_AT": "5"})
    r = run_group(cmd, env=env, timeout=300)
    assert r.returncode == 0, r.stderr[-3000:]
    assert "from step 4" in r.stdout  # the restarted attempt resumed
    assert torchelastic_left(tmp) == []  # torchrun's log folder went with the job
    state = checkpoint.load(out)
    split = Catalog.from_dict(state["catalog"]).split("train")
    assert state["epoch"] == 2 and state["step"] == 2 * steps_per_epoch(len(split), 2, 2)
    lines = sample_lines(out)
    assert lines.count("params " + lines[-1].split()[1]) == 1  # one finished attempt
    assert lines[-1] == sample_lines(out, 1)[-1]


def steps_per_epoch(n: int, world: int, batch: int) -> int:
    return -(-n // (world * batch))


def test_a_time_limit_stops_the_run_with_a_checkpoint_and_resume_goes_on(tiny_store, tmp_path):
    """``--time-limit``: on one process the run stops after the step where its time is up
    (here the first), with a checkpoint mid-epoch and the CLI's line saying so; ``--resume``
    trains the rest, in the order of a run never stopped. Under torchrun both ranks stop at
    the first epoch's end."""
    kw = {"epochs": 2, "lr_schedule": "constant", "log_samples": True}
    ref = tmp_path / "ref"
    train(config(tiny_store, ref, **kw))
    run = tmp_path / "cut"
    r = CliRunner().invoke(trainer_main, ["train", *argv(tiny_store, run, **kw, time_limit=1e-6)])
    assert r.exit_code == 0, r.output
    assert "stopped by --time-limit 1e-06: --resume goes on from here" in r.output
    state = checkpoint.load(run)
    assert (state["step"], state["epoch"], state["position"]) == (1, 0, 2)
    summary = train(config(tiny_store, run, **kw, resume=True))
    assert not summary["timed_out"] and summary["steps"] == checkpoint.load(ref)["step"]
    assert sample_lines(run)[-1] == sample_lines(ref)[-1]  # the same weights at the end

    out = tmp_path / "ddp"
    cmd = [sys.executable, "-m", "trainer.cli", "launch", "--nproc-per-node", "2"]
    cmd += [*argv(tiny_store, out, epochs=3), "--time-limit", "1e-6"]
    r = run_group(cmd, timeout=300)
    assert r.returncode == 0 and "stopped by --time-limit" in r.stdout, r.stderr[-3000:]
    state = checkpoint.load(out)
    split = Catalog.from_dict(state["catalog"]).split("train")
    assert (state["epoch"], state["position"]) == (1, 0)
    assert state["step"] == steps_per_epoch(len(split), 2, 2)


def test_checkpoint_seconds_skips_epoch_end_saves_until_that_long_has_passed(tiny_store, tmp_path):
    """``--checkpoint-seconds``: an epoch that ends sooner than that after the last checkpoint
    (or the run's start) writes none, the run's end always does, and the weights are those of
    a run that saved at every epoch's end."""
    kw = {"epochs": 3, "lr_schedule": "constant", "log_samples": True, "val_samples": 0,
          "keep": 10, "checkpoint_every": 1000}  # fmt: skip
    ref, run = tmp_path / "ref", tmp_path / "run"
    train(config(tiny_store, ref, **kw))
    train(config(tiny_store, run, **kw, checkpoint_seconds=3600))
    steps = [checkpoint.load(p)["step"] for p in checkpoint.listing(ref)]
    assert steps == [9, 18, 27]  # every epoch's end
    assert [checkpoint.load(p)["step"] for p in checkpoint.listing(run)] == [27]  # the end
    assert sample_lines(run)[-1] == sample_lines(ref)[-1]
    train(config(tiny_store, run, **{**kw, "epochs": 4}, resume=True, checkpoint_seconds=3600))
    assert [checkpoint.load(p)["step"] for p in checkpoint.listing(run)] == [27, 36]


def test_launch_checks_inputs_before_torchrun_and_a_failed_rank_is_one_line(tiny_store, tmp_path):
    """Bad input stops ``trainer launch`` before any rank starts; a rank that dies later
    (here rank 0 at step 1, no restarts) ends it with one line naming the rank, not torchrun's
    traceback."""
    launch = [sys.executable, "-m", "trainer.cli", "launch", "--nproc-per-node", "2"]
    out = tmp_path / "run"
    missing = SimpleNamespace(url=str(tmp_path / "none.zarr"))
    r = run_group([*launch, *argv(missing, out)])
    assert r.returncode == 1 and r.stderr.startswith("Error: "), r.stderr  # nor torchrun's line
    assert len(r.stderr.strip().splitlines()) == 1 and "none.zarr: not a shard store" in r.stderr
    assert not out.exists()
    env, tmp = private_tmp(tmp_path, {**os.environ, "SHADERBALL_TRAIN_CRASH_AT": "1"})
    r = run_group([*launch, *argv(tiny_store, out, epochs=1)], env=env)
    last = r.stderr.strip().splitlines()[-1]
    assert r.returncode == 1 and last.startswith(
        "Error: rank 0 of the torchrun job failed with exit code 3"
    ), r.stderr[-3000:]
    assert torchelastic_left(tmp) == []
    # the other rank may print its own error (its peer is gone), prefixed "[rank1]:"; the
    # launcher prints none
    assert not any(line.startswith("Traceback") for line in r.stderr.splitlines())
    assert "ChildFailedError" not in r.stderr


def test_a_loader_worker_that_cannot_send_a_batch_stops_the_run_in_one_line(tiny_store, tmp_path):
    """A DataLoader worker that cannot hand a batch over (as when /dev/shm is full) exits,
    and the run stops in one line, where torch alone would wait for the batch forever."""
    env = {**os.environ, "SHADERBALL_TRAIN_UNSENDABLE": "1"}
    out = tmp_path / "lost"
    cmd = [sys.executable, "-m", "trainer.cli", "train", *argv(tiny_store, out, workers=2)]
    r = run_group(cmd, env=env, timeout=120)
    last = r.stderr.strip().splitlines()[-1]
    # the last line: the other worker, even one still starting, is stopped before the exit
    assert r.returncode == 1 and re.match(
        r"Error: DataLoader worker \(pid(\(s\))? [\d, ]+\) exited unexpectedly.* \(its error is ",
        last,
    ), r.stderr[-3000:]
    assert "cannot pickle" in r.stderr and "could not send a batch: exiting" in r.stderr
    assert "done:" not in r.stdout


@pytest.mark.parametrize(
    "epochs, says",
    [
        (1, r"ended epoch 1 after \d+ of this rank's \d+ batches"),
        (2, r"out of step \(a batch of epoch 2 in epoch 1\)"),
    ],
)
def test_an_epoch_short_of_a_batch_stops_the_run(tiny_store, tmp_path, monkeypatch, epochs, says):
    """Batches lost on the way (a loader that skips its second) stop the run: the last epoch
    ends short, or an earlier one gets the next epoch's batch."""
    real = train_module.loader

    class SkipsOne:
        def __init__(self, stream, workers, pin_memory=False):
            self.stream = stream

        def __iter__(self):
            return (b for k, b in enumerate(real(self.stream, 0)) if k != 1)

    monkeypatch.setattr(train_module, "loader", SkipsOne)
    with pytest.raises(train_module.LoaderError, match=says):
        train(config(tiny_store, tmp_path / "run", epochs=epochs))


def test_launch_refuses_a_dev_shm_too_small_for_the_loaders(tiny_store, tmp_path):
    """Under a 1 MB /dev/shm (a private mount, where this machine allows one) the launcher
    stops in one line before any rank starts, and a lone `trainer train` does too."""
    probe = subprocess.run(["unshare", "-m", "true"], capture_output=True)
    if probe.returncode != 0:
        pytest.skip(f"no private mount namespace here: {probe.stderr.decode().strip()}")
    out = tmp_path / "run"
    for command in ("launch", "train"):
        cmd = [sys.executable, "-m", "trainer.cli", command, *argv(tiny_store, out, workers=2)]
        script = "mount -t tmpfs -o size=1m tmpfs /dev/shm && exec " + shlex.join(cmd)
        r = run_group(["unshare", "-m", "sh", "-c", script])
        last = r.stderr.strip().splitlines()[-1]
        assert r.returncode == 1 and last.startswith("Error: /dev/shm has 1.0 MB free"), r.stderr
        assert "--workers" in last and "Traceback" not in r.stderr
        assert not out.exists()


def test_sigterm_to_the_launcher_stops_every_rank(tiny_store, tmp_path):
    cmd = [sys.executable, "-m", "trainer.cli", "launch", "--nproc-per-node", "2"]
    cmd += argv(tiny_store, tmp_path / "run", epochs=500)
    env, tmp = private_tmp(tmp_path)
    proc = subprocess.Popen(
        cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, start_new_session=True,
        env=env,
    )  # fmt: skip
    try:
        deadline = time.time() + 120
        ranks = []
        while time.time() < deadline and len(ranks) < 2:
            time.sleep(0.5)
            ranks = psutil.Process(proc.pid).children(recursive=True)
            ranks = [p for p in ranks if "trainer.cli" in " ".join(p.cmdline())]
        assert len(ranks) == 2, "the ranks did not start"
        time.sleep(3)
        proc.send_signal(signal.SIGTERM)
        _, err = proc.communicate(timeout=60)
        assert proc.returncode == 128 + signal.SIGTERM, err[-2000:]
        gone, alive = psutil.wait_procs(ranks, timeout=10)
        assert not alive
        assert torchelastic_left(tmp) == []
    finally:
        with contextlib.suppress(ProcessLookupError):
            os.killpg(proc.pid, signal.SIGKILL)


def test_the_zsolnai_feher_baseline_trains_saves_loads_and_evaluates(tiny_store, tmp_path):
    from trainer.zf import ZsolnaiFeherRenderer, material_vector

    out = tmp_path / "zf"
    train(config(tiny_store, out, epochs=4, model="zf", lr=3e-4))
    state = checkpoint.load(out)
    assert state["model_config"]["arch"] == "zf"
    catalog = Catalog.from_dict(state["catalog"])
    torch.manual_seed(0)  # the run's initial weights
    before = mean_l1(ZsolnaiFeherRenderer(ModelConfig(resolution=64, arch="zf")), catalog)
    renderer = Renderer.from_checkpoint(out)
    assert isinstance(renderer.model, ZsolnaiFeherRenderer)
    assert mean_l1(renderer.model, catalog) < 0.9 * before
    maps = tiny_store.read_shard(0).maps[0]
    a = renderer.render(maps, (0, 0, 1), 3)
    b = renderer.render(maps, (0.8, 0, 0.6), 8)
    np.testing.assert_array_equal(a, b)  # no light input: one image per material
    x = model_inputs(torch.from_numpy(maps[None]))
    ball = x[:, -1:] > 0.25
    np.testing.assert_allclose(  # the material's values: each channel's mean over the ball
        material_vector(x)[0, :3].numpy(), [float(x[0, c][ball[0, 0]].mean()) for c in range(3)],
        rtol=1e-5,
    )  # fmt: skip
    r = CliRunner().invoke(trainer_main, ["eval", "--checkpoint", str(out), "--json"])
    assert r.exit_code == 0, r.output
    assert json.loads(r.output[r.output.index("{") :])["overall"]["n"] > 0
    import onnxruntime as ort

    from trainer.rendering.export import export

    for opset in (18, 15):  # exports as well, through both exporters, with every input
        assert export(renderer, tmp_path / f"zf{opset}.onnx", opset).max_difference < 1e-4
        session = ort.InferenceSession(str(tmp_path / f"zf{opset}.onnx"))
        assert [i.name for i in session.get_inputs()] == ["maps", "sun", "turbidity"]


def test_the_shared_memory_check_counts_a_batch_as_the_loader_makes_it(tiny_store):
    from trainer.samples import SampleReader
    from trainer.training.shm import batch_bytes

    split = Catalog.snapshot([tiny_store.url], 0, 0.25, None).split("train")
    batch = SampleReader(split).batch(np.arange(3))
    sent = sum(t.numel() * t.element_size() for t in batch.values())
    assert sent == batch_bytes(tiny_store.layout.resolution, 3)


# ---- the default recipe ----------------------------------------------------------------------

#: the default recipe at a small width (GroupNorm's 8 groups need a multiple of 8)
DEFAULT = {"width": 8, "batch_size": 2, "holdout_fraction": 0.25, "workers": 0, "log_every": 2,
           "max_steps": 6, "epochs": 2}  # fmt: skip


@pytest.fixture(scope="module")
def trained_default(tiny_store, tmp_path_factory):
    """A short run of the default recipe (scene cues, GroupNorm, MS-SSIM, one-cycle, a weight
    average) on the tiny store: its folder."""
    out = tmp_path_factory.mktemp("default") / "run"
    train(TrainConfig(store=(tiny_store.url,), out=str(out), **DEFAULT))
    return out


def test_the_default_recipe_keeps_its_network_and_scene_in_its_checkpoints(
    tiny_store, trained_default, tmp_path
):
    state = checkpoint.load(trained_default)
    assert state["config"]["recipe"] == "shaderball"
    cfg = ModelConfig(**state["model_config"])
    assert cfg.inputs == TrainConfig(store=("s",)).inputs and cfg.norm == "group" and not cfg.head
    assert state["schedule"]["schedule"] == "onecycle" and state.get("ema") is not None
    r = Renderer.from_checkpoint(trained_default)  # built without the store: from the weights
    buffers = r.model.scene.position
    assert buffers.abs().sum() > 0
    layout = tiny_store.screen_uv().geometry
    np.testing.assert_array_equal(buffers.numpy(), layout.position)
    maps = tiny_store.packed_maps(0)
    sun, turbidity = tiny_store.light(0)
    image = r.render(maps, sun, turbidity)
    assert image.shape == (3, 64, 64) and image.min() >= 0 and image.max() <= 1
    out = tmp_path / "r.png"
    args = ["render", "--checkpoint", str(trained_default), "--material", "procedural:seed=3",
            "--sun", "0.3,-0.5,0.8", "-o", str(out)]  # fmt: skip
    assert CliRunner().invoke(trainer_main, args).exit_code == 0 and out.exists()
    result = evaluate(trained_default)
    assert result["overall"]["n"] > 0 and result["overall"]["psnr"] > 5


@pytest.mark.parametrize("opset", [18, 11])
def test_the_default_recipes_network_exports_to_onnx_with_its_scene(
    tiny_store, trained_default, tmp_path, opset
):
    """The scene cues are part of the exported graph: the model takes stored maps and the
    sun as the paper's does, and ONNX Runtime renders what the checkpoint renders (export
    checks it before it keeps the file)."""
    onnx = tmp_path / "ball.onnx"
    r = CliRunner().invoke(trainer_main, ["export", "--checkpoint", str(trained_default), "-o",
                                          str(onnx), "--opset", str(opset)])  # fmt: skip
    assert r.exit_code == 0, r.output
    model = load_renderer(onnx)
    maps = tiny_store.packed_maps(1)
    sun, turbidity = tiny_store.light(2)
    want = Renderer.from_checkpoint(trained_default).render(maps, sun, turbidity)
    np.testing.assert_allclose(model.render(maps, sun, turbidity), want, atol=1e-4)


def test_a_slimmed_checkpoint_renders_as_its_run_and_starts_runs_but_resumes_none(
    tiny_store, trained_default, tmp_path
):
    """``trainer slim``: the run's average in float16, the scene's buffers as they were, no
    optimizer state; it renders within float16's rounding of the run, eval scores its
    held-out split, ``--init`` starts a run from it; asking for the weights it dropped, a
    resume from it and a name that is not .pt are one-line errors."""
    from trainer.slim import parameter_names

    out = tmp_path / "share" / "ball.pt"
    r = CliRunner().invoke(trainer_main, ["slim", "--checkpoint", str(trained_default), "-o",
                                          str(out)])  # fmt: skip
    assert r.exit_code == 0, r.output
    assert f"wrote {out} (" in r.output and "the average weights of step 6 in float16" in r.output
    whole, slim = checkpoint.load(trained_default), checkpoint.load(out)
    assert slim["slim"] == {"weights": "average", "dtype": "float16"}
    assert "optimizer" not in slim and "ema" not in slim and slim["catalog"] == whole["catalog"]
    params = parameter_names(whole)
    average = whole["ema"]["weights"]
    for name, value in slim["model"].items():
        want = torch.float16 if name in params else average[name].dtype
        assert value.dtype == want, name
        assert torch.equal(value, average[name].to(want)), name
    assert any(n.startswith("scene.") for n in slim["model"]) and params < set(slim["model"])
    assert out.stat().st_size < checkpoint.latest(trained_default).stat().st_size

    renderer = Renderer.from_checkpoint(out)
    assert renderer.weights == "average" and renderer.step == 6
    maps = tiny_store.packed_maps(1)
    sun, turbidity = tiny_store.light(2)
    want = Renderer.from_checkpoint(trained_default).render(maps, sun, turbidity)
    got = renderer.render(maps, sun, turbidity)
    assert 0 < np.abs(got - want).max() < 2e-2  # rounded, and only by a little
    assert evaluate(out)["overall"]["n"] == evaluate(trained_default)["overall"]["n"]
    tuned = tmp_path / "tuned"
    train(TrainConfig(store=(tiny_store.url,), out=str(tuned), init=str(out), **DEFAULT))
    assert checkpoint.load(tuned)["step"] == 6

    msg = one_line_error(["eval", "--checkpoint", str(out), "--weights", "trained"])
    assert "keeps the average weights alone (slim the run's own checkpoint with --weights" in msg
    kept = tmp_path / "resumed" / runfiles.CHECKPOINTS
    kept.mkdir(parents=True)
    (kept / "step-00000006.pt").write_bytes(out.read_bytes())
    with pytest.raises(RunError, match="a slimmed checkpoint .* start a new run from it with"):
        train(TrainConfig(store=(tiny_store.url,), out=str(kept.parent), resume=True, **DEFAULT))
    r = CliRunner().invoke(trainer_main, ["slim", "--checkpoint", str(out), "-o", "b.onnx"])
    assert r.exit_code == 2 and "'b.onnx' does not end in .pt" in r.output
    msg = one_line_error(["slim", "--checkpoint", str(out), "-o", str(out)])
    assert msg == f"Error: {out}: is the checkpoint it slims; name another file"


def test_a_gpu_learn_calls_files_are_put_in_place_and_its_networks_scored(
    tiny_store, trained_default, tmp_path, capsys
):
    """``benchmarks.gpu_learn_back``: the table (with its grid's note) and grid go where the
    report reads them, each row's parts are joined into the slimmed checkpoint they were cut
    from, the rows' archive is unpacked, and trainer eval scores the networks on the run's
    held-out split, an earlier call's rows replaced; a part or the table missing, or an
    archive that does not unpack, is one line (exit 2) before anything is written."""
    import tarfile

    from benchmarks import gpu_learn_back, results

    back, into = tmp_path / "back", tmp_path / "into"
    back.mkdir()
    slim = tmp_path / "default.pt"
    assert CliRunner().invoke(trainer_main, ["slim", "--checkpoint", str(trained_default), "-o",
                                             str(slim)]).exit_code == 0  # fmt: skip
    whole = slim.read_bytes()
    (back / "learning-default.pt.0").write_bytes(whole[:1000])
    (back / "learning-default.pt.1").write_bytes(whole[1000:])
    table = results.Table("t", ["row", "PSNR dB"], [["paper", 1.0], ["default", 2.0]])
    results.save("learning-gpu", table, back)
    (back / "learning-gpu.png").write_bytes(b"png")
    (tmp_path / "64" / "8" / "default").mkdir(parents=True)
    (tmp_path / "64" / "8" / "default" / "log.jsonl").write_text("{}")
    with tarfile.open(back / "learning-rows.tgz", "w:gz") as tar:
        tar.add(tmp_path / "64", "64")
    kept = {"--results": tmp_path / "results", "--pictures": tmp_path / "pictures"}
    for folder in kept.values():
        folder.mkdir()
    args = [str(back), "--into", str(into), "--store", tiny_store.url, "--on", ""]
    args += [str(x) for pair in kept.items() for x in pair]

    def refused(said: str) -> None:
        with pytest.raises(SystemExit) as stopped:
            gpu_learn_back.main(args)
        assert stopped.value.code == 2 and said in capsys.readouterr().err
        assert not (into / "rows").exists() and not any((tmp_path / "results").iterdir())

    (back / "learning-paper.pt.1").write_bytes(b"a part without its first")
    refused("learning-paper.pt.0 is missing")
    assert not into.exists()
    (back / "learning-paper.pt.1").unlink()
    (back / "learning-gpu.json").rename(back / "table")
    refused("learning-gpu.json is missing: the call wrote no table")
    (back / "table").rename(back / "learning-gpu.json")
    (back / "learning-rows.tgz").rename(back / "archive")
    (back / "learning-rows.tgz").write_bytes(b"not gzip")
    refused("learning-rows.tgz: not an archive that unpacks")
    (back / "archive").replace(back / "learning-rows.tgz")
    (into / "rows" / "stale").mkdir(parents=True)  # an earlier call's files are replaced

    gpu_learn_back.main(args)
    said = capsys.readouterr().out
    assert (into / "default.pt").read_bytes() == whole
    assert (into / "rows" / "64" / "8" / "default" / "log.jsonl").read_text() == "{}"
    assert sorted(x.name for x in (into / "rows").iterdir()) == ["64"]
    assert [x.name for x in into.iterdir() if x.name.startswith(".")] == []
    saved = results.load(tmp_path / "results" / "learning-gpu.json")
    assert saved.notes == ["truth, paper, default and their errors on the same held-out "
                           "samples: ![learning-gpu](img/learning-gpu.png)"]  # fmt: skip
    assert (tmp_path / "pictures" / "learning-gpu.png").read_bytes() == b"png"
    heldout = (into / "eval-heldout.txt").read_text()
    assert "step 6 (the run's moving average): 6 held-out samples" in heldout and heldout in said
    assert (into / "eval-heldout.png").exists() and not (into / "eval-unseen.txt").exists()


def test_preloaded_batches_train_the_same_weights_as_the_loaders(tiny_store, tmp_path, monkeypatch):
    """``--preload`` takes the same batches in the same order from memory, with each sample's
    target and scene cues made once, in place of its render and maps (or, over
    ``PRELOAD_CUES_BYTES``, the maps kept and the cues made in each step): the same weights
    to the bit."""
    from trainer.training import train as loop

    step, seen = loop.train_step, []

    def noting(cfg, rk, t, batch):
        seen.append(sorted(k for k in batch if k in ("cues", "maps", "render", "target")))
        return step(cfg, rk, t, batch)

    monkeypatch.setattr(loop, "train_step", noting)
    weights = []
    for i, (preload, cap) in enumerate(((False, None), (True, None), (True, 0))):
        if cap is not None:
            monkeypatch.setattr(loop, "PRELOAD_CUES_BYTES", cap)
        out, seen[:] = tmp_path / f"run{i}", []
        train(TrainConfig(store=(tiny_store.url,), out=str(out), preload=preload,
                          **(DEFAULT | {"max_steps": 4, "ema_decay": 0.0})))  # fmt: skip
        weights.append(checkpoint.load(out)["model"])
        # what each batch brought along: from memory, only what its step reads
        made = [["maps", "render"], ["cues", "target"], ["maps", "target"]][i]
        assert seen == [made] * 4
    for other in weights[1:]:
        for name, w in weights[0].items():
            torch.testing.assert_close(other[name], w, atol=0, rtol=0, msg=name)


def test_a_store_without_scene_buffers_is_refused_by_the_default_recipe_in_one_line(
    tiny_store, tmp_path
):
    """A store made before the buffers: the default recipe stops in one line naming the
    command that adds them, and writes nothing; the paper's recipe trains on it."""
    import shutil

    from render_jobs.screen_uv import FILE

    old = tmp_path / "old.zarr"
    shutil.copytree(tiny_store.url, old)
    layout = dataclasses.replace(tiny_store.screen_uv(), geometry=None)
    (old / FILE).write_bytes(layout.to_bytes())
    r = run_group([sys.executable, "-m", "trainer.cli", "train", "--store", str(old), "--out",
                   str(tmp_path / "run"), "--max-steps", "1", "--width", "8"])  # fmt: skip
    assert r.returncode == 1 and "farm screen-uv" in r.stderr, r.stderr
    assert len(r.stderr.strip().splitlines()) == 1 and not (tmp_path / "run").exists()
    train(TrainConfig(store=(str(old),), out=str(tmp_path / "paper"), recipe="paper",
                      loss="l1", **(DEFAULT | {"max_steps": 1})))  # fmt: skip
