"""The command lines: help everywhere, `farm preview` end to end, and its bad-input paths."""

from __future__ import annotations

import contextlib
import json
import os
import shutil
import signal
import subprocess
import sys
import tarfile
import time
from pathlib import Path

import click
import numpy as np
import psutil
import pytest
from PIL import Image

from farm.cli import main as farm_main
from render_jobs.exr import read_layers
from storage.cli import main as shards_main
from trainer.cli import main as trainer_main

BIN = Path(sys.executable).parent


def walk(group: click.Group, prefix: str):
    yield prefix, group
    for name, cmd in group.commands.items():
        if isinstance(cmd, click.Group):
            yield from walk(cmd, f"{prefix} {name}")
        else:
            yield f"{prefix} {name}", cmd


@pytest.mark.parametrize(
    "group,name", [(farm_main, "farm"), (shards_main, "shards"), (trainer_main, "trainer")]
)
def test_every_command_has_help(group, name):
    for path, cmd in walk(group, name):
        assert cmd.help and len(cmd.help.strip()) > 20, f"{path} has no help"
        if isinstance(cmd, click.Group):  # the group's own page shows commands to type
            lines = [line.strip() for line in cmd.help.splitlines()]
            assert any(line.startswith(f"{path} ") for line in lines), f"{path} shows no example"
        else:
            assert "Example" in cmd.help, f"{path}'s help shows no example"
            for param in cmd.params:
                if isinstance(param, click.Option):
                    assert param.help, f"{path} {param.opts[0]} has no help"


def run(*args, cwd=None, env=None):
    return subprocess.run(
        [str(BIN / args[0]), *args[1:]],
        capture_output=True, text=True, cwd=cwd, timeout=300, env=env,
    )  # fmt: skip


@pytest.mark.slow
def test_farm_preview_writes_maps_renders_and_a_contact_sheet(tmp_path):
    out = tmp_path / "preview"
    # the bar's lines as a log gets them, one at every redraw
    every = {**os.environ, "SHADERBALL_PROGRESS_S": "0"}
    args = ["-m", "procedural", "--suns", "2", "--resolution", "48", "--samples", "4",
            "--seed", "3", "--threads", "2", "-o", str(out)]  # fmt: skip
    r = run("farm", "preview", *args, env=every)
    assert r.returncode == 0, r.stderr
    assert "contact_sheet.png" in r.stdout
    lines = r.stderr.splitlines()
    assert "\r" not in r.stderr  # whole lines, the first from before Blender loads
    assert any("| 0/2 [" in ln for ln in lines) and any("| 2/2 [" in ln for ln in lines)
    names = {p.name for p in out.iterdir()}
    for n in (
        "maps.exr",
        "contact_sheet.png",
        "preview.json",
        "sun_0.exr",
        "sun_1.png",
        "map_diffuse.png",
        "map_normal.png",
        "map_mask.png",
    ):
        assert n in names
    layers = read_layers(out / "maps.exr")
    assert layers["diffuse"].shape == (3, 48, 48) and layers["mask"].shape == (1, 48, 48)
    assert read_layers(out / "sun_1.exr")[""].shape == (3, 48, 48)
    meta = json.loads((out / "preview.json").read_text())
    assert meta["material"]["kind"] == "procedural" and len(meta["renders"]) == 2
    assert meta["settings"]["samples"] == 4 and len(meta["geometry_hash"]) == 64
    sheet = Image.open(out / "contact_sheet.png")
    assert sheet.width == 5 * 48 and sheet.height > 2 * 48
    assert not [p for p in tmp_path.iterdir() if p.name.startswith(".")]  # no temp left


@pytest.mark.parametrize(
    "material,needle",
    [
        ("nope.png", "nope.png: no such file or folder"),
        ("bad.png", "bad.png: not a readable image"),
        ("wide.png", "wide.png: expected 5 square panels"),
    ],
)
def test_farm_preview_bad_material_is_one_line_and_writes_nothing(tmp_path, material, needle):
    (tmp_path / "bad.png").write_bytes(b"not a png")
    Image.fromarray(np.zeros((8, 24, 3), np.uint8)).save(tmp_path / "wide.png")
    r = run("farm", "preview", "-m", material, "-o", "out", cwd=tmp_path)
    assert r.returncode == 1
    lines = r.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("Error: ") and needle in lines[0], r.stderr
    assert "Traceback" not in r.stderr
    assert not (tmp_path / "out").exists()


def test_farm_preview_to_a_folder_it_cannot_write_fails_before_rendering(tmp_path):
    (tmp_path / "file").write_text("")
    r = run("farm", "preview", "-m", "uniform", "-o", "file/out", "--resolution", "16",
            "--samples", "1", cwd=tmp_path)  # fmt: skip
    lines = r.stderr.strip().splitlines()
    assert r.returncode == 1 and len(lines) == 1, r.stderr
    assert lines[0].startswith("Error: FileExistsError") and "file" in lines[0]
    assert "rendering" not in r.stderr  # nothing rendered first


@pytest.mark.parametrize("after_s", [0, 4], ids=["while-blender-loads", "mid-frame"])
def test_a_preview_stopped_by_sigterm_leaves_no_folder_and_no_blender(tmp_path, after_s):
    """SIGTERM (``timeout``, a closed terminal's job control) unwinds as Ctrl-C does: the
    temporary folder and the Blender child go at once (a frame here takes minutes), and the
    exit says which signal."""
    proc = subprocess.Popen(
        [str(BIN / "farm"), "preview", "-m", "uniform", "-o", str(tmp_path / "out"),
         "--resolution", "400", "--samples", "4096"],
        stderr=subprocess.PIPE, text=True,
    )  # fmt: skip
    deadline = time.monotonic() + 120
    blender = []
    while not blender and time.monotonic() < deadline:  # the child has mapped bpy
        time.sleep(0.2)
        kids = psutil.Process(proc.pid).children(recursive=True)
        blender = [k for k in kids if _maps_bpy(k)]
    assert blender, "no Blender child started"
    time.sleep(after_s)  # a start takes about 1.5 s here
    proc.send_signal(signal.SIGTERM)
    sent = time.monotonic()
    err = proc.communicate(timeout=60)[1]
    assert time.monotonic() - sent < 8  # not the 10 s a polite close gives a busy child
    assert proc.returncode == 128 + signal.SIGTERM, err
    last = err.strip().splitlines()[-1]
    assert last == f"SIGTERM: stopped; nothing was written to {tmp_path / 'out'}", err
    assert os.listdir(tmp_path) == []  # neither the output nor the temporary folder
    gone, alive = psutil.wait_procs(blender, timeout=10)
    assert not alive, alive


def _maps_bpy(proc: psutil.Process) -> bool:
    with contextlib.suppress(psutil.Error):
        return any("bpy" in m.path for m in proc.memory_maps())
    return False


def test_bad_option_values_are_refused(tmp_path):
    r = run("farm", "preview", "-m", "uniform", "--resolution", "2", "-o", str(tmp_path / "o"))
    assert r.returncode == 2 and "--resolution" in r.stderr


@pytest.mark.parametrize("value", ["x", "-1", "inf", "nan"])
def test_a_bad_progress_setting_is_one_line_before_a_command_writes(tmp_path, value):
    env = {**os.environ, "SHADERBALL_PROGRESS_S": value}
    out = tmp_path / "o"
    for cmd in (["farm", "preview", "-m", "uniform", "-o", str(out)], ["shards", "ls", str(out)],
                ["trainer", "launch", "--store", str(out), "--out", str(out)]):  # fmt: skip
        r = run(*cmd, env=env)
        assert r.returncode == 1 and not out.exists(), r.stderr
        assert r.stderr.strip().splitlines() == [
            f"Error: SHADERBALL_PROGRESS_S={value!r}: expected a number of seconds, 0 or more"
        ]


@pytest.mark.parametrize(
    "command",
    [
        "shards ls {url}",
        "shards verify {url}",
        "farm status {url}",
        "farm cancel {url}",
        "farm screen-uv {url}",
        "trainer launch --store {url} --out {tmp}/run --max-steps 1",
    ],
)
def test_a_store_out_of_reach_ends_every_command_in_one_line(tmp_path, command):
    """An S3 endpoint nobody listens on: after the retries, the error and its endpoint in
    one line (the click group's handler of ``OSError``), no traceback. ``trainer viewer``:
    ``tests/test_viewer.py``."""
    from tests.conftest import free_port, s3_env

    env = {**os.environ, **s3_env(f"http://127.0.0.1:{free_port()}", AWS_MAX_ATTEMPTS="1",
                                  SHADERBALL_STORE_RETRY_S="1")}  # fmt: skip
    name, *args = command.format(url="s3://shaderball/gone.zarr", tmp=tmp_path).split()
    r = subprocess.run([str(BIN / name), *args], env=env, capture_output=True, text=True,
                       timeout=120)  # fmt: skip
    assert r.returncode == 1 and "Traceback" not in r.stderr, r.stderr[-3000:]
    last = r.stderr.strip().splitlines()[-1]
    assert last.startswith("Error: ") and "EndpointConnectionError" in last, last
    assert "StoreUnreachable" in last and "127.0.0.1" in last


def test_a_bad_retry_setting_is_one_line(tmp_path):
    env = {**os.environ, "SHADERBALL_STORE_RETRY_S": "soon"}
    r = subprocess.run([str(BIN / "shards"), "ls", str(tmp_path)], env=env,
                       capture_output=True, text=True)  # fmt: skip
    assert r.returncode == 1 and "Traceback" not in r.stderr, r.stderr
    want = "Error: SHADERBALL_STORE_RETRY_S='soon': expected a number of seconds above 0"
    assert r.stderr.strip() == want


def test_no_process_but_a_blender_worker_imports_bpy():
    code = (
        "import sys\n"
        "import farm, farm.cli, storage, storage.cli, trainer, trainer.cli\n"
        "import trainer.training.train\n"
        "import trainer.rendering.evaluate, trainer.rendering.infer, trainer.training.launch\n"
        "import render_jobs, render_jobs.materials, render_jobs.preview, render_jobs.process\n"
        "import render_jobs.geometry, render_jobs.sun, render_jobs.exr\n"
        "assert 'bpy' not in sys.modules, 'bpy was imported'\n"
        "try:\n"
        "    import render_jobs.blender.renderer\n"
        "except ImportError as e:\n"
        "    assert 'Blender worker process' in str(e)\n"
        "else:\n"
        "    raise SystemExit('render_jobs.blender imported outside a worker')\n"
        "assert 'bpy' not in sys.modules\n"
        "print('clean')\n"
    )
    env = {k: v for k, v in os.environ.items() if k != "SHADERBALL_BLENDER_WORKER"}
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env)
    assert r.returncode == 0 and r.stdout.strip() == "clean", r.stderr


def test_gpu_benchmark_script_refuses_bad_use(tmp_path):
    """``benchmarks/gpu.sh`` (run on a GPU machine) stops with one line and exit 2 on a
    missing part or a missing store, before it installs or runs anything."""
    script = Path(__file__).parents[1] / "benchmarks" / "gpu.sh"
    r = subprocess.run(["bash", str(script), "bogus"], capture_output=True, text=True)
    usage = "usage: bash benchmarks/gpu.sh learn|infer|train|viewer [ARGS]\n"
    assert (r.returncode, r.stderr) == (2, usage)
    r = subprocess.run(["bash", str(script), "train", "--x"], capture_output=True, text=True)
    assert (r.returncode, r.stderr) == (2, "gpu.sh: train takes no arguments\n")
    (tmp_path / "benchmarks").mkdir()  # a checkout without the carried store and layouts
    copy = tmp_path / "benchmarks" / "gpu.sh"
    copy.write_text(script.read_text())
    for part, missing in (("infer", "out/bench-400.zarr is missing"),
                          ("viewer", "benchmarks/.cache has no screen UV layouts")):  # fmt: skip
        r = subprocess.run(["bash", str(copy), part], capture_output=True, text=True)
        assert r.returncode == 2 and missing in r.stderr
        assert len(r.stderr.splitlines()) == 1 and not (tmp_path / "out").exists()


def gpu_checkout(root: Path, module: str, source: str, store: str | None = None) -> None:
    """A checkout at ``root`` as a device call gets it: ``benchmarks/gpu.sh``, a stand-in
    ``benchmarks.<module>`` (``source``) and, where a part reads one, an empty carried store."""
    script = Path(__file__).parents[1] / "benchmarks" / "gpu.sh"
    (root / "benchmarks").mkdir(exist_ok=True)
    (root / "benchmarks" / "gpu.sh").write_text(script.read_text())
    (root / "benchmarks" / f"{module}.py").write_text(source)
    (root / "benchmarks" / "__init__.py").touch()
    if store is not None:
        (root / "out" / store).mkdir(parents=True)
        (root / "out" / store / "zarr.json").write_text("{}")


def test_gpu_benchmark_script_runs_the_viewer_benchmark_on_cuda(tmp_path):
    """``gpu.sh viewer [ARGS]`` runs ``benchmarks.viewer --device cuda [ARGS]`` on the carried
    layouts."""
    gpu_checkout(tmp_path, "viewer", "import sys; print('args', sys.argv[1:])")
    (tmp_path / "benchmarks" / ".cache").mkdir()
    (tmp_path / "benchmarks" / ".cache" / "screen_uv-128-4.npz").touch()
    env = {**os.environ, "PYTHON": sys.executable, "OUT": str(tmp_path / "device-out")}
    for extra in ([], ["--runtimes", "torch,graph"]):
        r = subprocess.run(["bash", "benchmarks/gpu.sh", "viewer", *extra], cwd=tmp_path,
                           env=env, capture_output=True, text=True)  # fmt: skip
        assert r.returncode == 0, r.stderr
        log = (tmp_path / "device-out" / "gpu-bench.txt").read_text()
        assert f"args {['--device', 'cuda', *extra]}" in log


# stands in for benchmarks.learning: says its arguments, writes a run folder for each row (a
# checkpoint too) under --work and the table and its grid under --results
FAKE_LEARNING = """
import argparse, pathlib, sys
print("args", sys.argv[1:], flush=True)
p = argparse.ArgumentParser()
for name in ("--rows", "--work", "--budget", "--results", "--name"):
    p.add_argument(name)
arg, _ = p.parse_known_args()
for row in arg.rows.split(","):
    run = pathlib.Path(arg.work, "64", arg.budget, row)
    (run / "checkpoints").mkdir(parents=True)
    for name in ("grid.png", "log.jsonl", "result.json", "checkpoints/step-1.pt"):
        (run / name).write_text(row + " " + name)
for ext in ("json", "png"):
    pathlib.Path(arg.results, arg.name + "." + ext).write_text("table")
"""


# stands in for ``trainer slim``: writes FAKE_SLIM_MB MiB (20 by default) for a run named
# default, 1,000 bytes for any other
FAKE_SLIM = """
import os, pathlib, sys
args = sys.argv[1:]
assert args[0] == "slim", args
run, out = args[args.index("--checkpoint") + 1], args[args.index("-o") + 1]
size = int(float(os.environ.get("FAKE_SLIM_MB", "20")) * 2**20) if run.endswith("default") else 1000
pathlib.Path(out).write_bytes(bytes(range(256)) * (size // 256))
print("wrote", out)
"""


def test_gpu_benchmark_script_trains_both_learning_rows_at_their_rates(tmp_path):
    """``gpu.sh learn`` runs ``benchmarks.learning`` on the carried store at the paper's length,
    the default's rate scaled by the root of the batch ratio and the paper's at its own
    (``LR_SCALE`` replaces those rules), the paper's row first within its cap and the default
    in the rest of the call (``ROW_SECONDS`` replaces the caps); the runs go to a folder of
    their own and ``$OUT`` gets only what a device call brings back: at most 8 files, 2
    folders down at most, 60 MiB in all: the rows' grids and logs in one archive and each
    row's slimmed network in parts of 15 MiB, unless it would pass that."""
    gpu_checkout(tmp_path, "learning", FAKE_LEARNING, "gpu-learn-64-1100.zarr")
    (tmp_path / "trainer").mkdir()
    (tmp_path / "trainer" / "__init__.py").touch()
    (tmp_path / "trainer" / "cli.py").write_text(FAKE_SLIM)
    seen: set[Path] = set()  # the earlier calls' runs
    for call, (extra, rules, row_caps) in enumerate((
        ({}, ["sqrt", "paper=none"], ["paper=200"]),
        ({"LR_SCALE": "linear", "ROW_SECONDS": "100 default=300", "FAKE_SLIM_MB": "61"},
         ["linear"], ["100", "default=300"]),
    )):  # fmt: skip
        out = tmp_path / f"device-out-{call}"
        # TMPDIR: where gpu.sh makes the runs' folder
        env = {**os.environ, "PYTHON": sys.executable, "OUT": str(out), "TMPDIR": str(tmp_path)}
        env |= extra
        r = subprocess.run(["bash", "benchmarks/gpu.sh", "learn"], cwd=tmp_path, env=env,
                           capture_output=True, text=True)  # fmt: skip
        assert r.returncode == 0, r.stderr
        scales = [x for rule in rules for x in ("--lr-scale", rule)]
        caps = [x for cap in row_caps for x in ("--row-seconds", cap)]
        said = ["--store", "out/gpu-learn-64-1100.zarr", "--device", "cuda", "--preload",
                "--budget", "1470000", "--batch", "128", *scales, "--rows", "paper,default",
                *caps, "--seconds", "520"]  # fmt: skip
        assert f"args {said}"[:-1] in r.stdout, r.stdout
        back = sorted(p.name for p in out.rglob("*"))
        weights = ["learning-default.pt.0", "learning-default.pt.1"] if call == 0 else []
        assert back == ["gpu-bench.txt", *weights, "learning-gpu.json", "learning-gpu.png",
                        "learning-paper.pt.0", "learning-rows.tgz"]  # fmt: skip
        assert all(p.stat().st_size <= 16 << 20 for p in out.iterdir())
        with tarfile.open(out / "learning-rows.tgz") as tar:
            kept = {m.name: tar.extractfile(m).read() for m in tar.getmembers() if m.isfile()}
        files = ("grid.png", "log.jsonl")
        names = [f"{row} {file}" for row in ("default", "paper") for file in files]
        assert kept == {f"64/1470000/{n.replace(' ', '/')}": n.encode() for n in names}
        (work,) = {p.parents[3] for p in tmp_path.glob("tmp.*/64/1470000/*/log.jsonl")} - seen
        seen.add(work)
        for row in ("default", "paper")[call:]:  # the parts make the file again
            parts = sorted(out.glob(f"learning-{row}.pt.*"))
            assert b"".join(p.read_bytes() for p in parts) == (work / f"{row}.pt").read_bytes()
        log = (out / "gpu-bench.txt").read_text()
        behind = "gpu.sh: default's network stays behind (over 8 files or 60 MiB to bring back)"
        assert (behind in log) == (call == 1)
    assert len(list(tmp_path.glob("tmp.*/64/1470000/paper/checkpoints/step-1.pt"))) == 2


# stands in for benchmarks.infer: says whether an earlier call's tuning is there, tunes "one
# operation" into Inductor's cache, then outlasts the budget as a long autotuning run does
SLOW_INFER = """
import os, pathlib, sys, time
cache = pathlib.Path(os.environ["TORCHINDUCTOR_CACHE_DIR"], "cache")
print("args", sys.argv[1:], "tuned before:", sorted(p.name for p in cache.glob("*")), flush=True)
cache.mkdir(parents=True, exist_ok=True)
(cache / f"op{len(list(cache.glob('*')))}").write_text("timings")
time.sleep(60)
"""


def test_gpu_benchmark_script_carries_autotuning_over_calls(tmp_path):
    """``gpu.sh infer`` stops the benchmark after ``BUDGET`` seconds, still packs Inductor's
    cache into ``$OUT/gpucache.tgz``, and a call given that cache in ``.gpucache/`` starts from
    it: a long autotuning run spreads over several device calls."""
    gpu_checkout(tmp_path, "infer", SLOW_INFER, "bench-400.zarr")
    env = {**os.environ, "PYTHON": sys.executable, "BUDGET": "6"}
    for call, before in enumerate([[], ["op0"]]):
        out = tmp_path / f"device-out-{call}"
        cmd = ["bash", "benchmarks/gpu.sh", "infer", "--only", "subpixel compiled"]
        r = subprocess.run(
            cmd, cwd=tmp_path, env={**env, "OUT": str(out)}, capture_output=True, text=True
        )
        assert r.returncode == 0, r.stderr
        assert "args ['--store', 'out/bench-400.zarr', '--batch', '128'" in r.stdout
        assert f"'--only', 'subpixel compiled'] tuned before: {before}" in r.stdout
        assert "benchmarks.infer ended with status 124" in r.stdout  # the budget stopped it
        assert "caches: " in r.stdout and (out / "gpu-bench.txt").exists()
        # what comes back from the device, unpacked into the next call's checkout
        shutil.rmtree(tmp_path / ".gpucache")
        (tmp_path / ".gpucache").mkdir()
        tar = ["tar", "-xzf", out / "gpucache.tgz", "-C", tmp_path / ".gpucache"]
        subprocess.run(tar, check=True)
    assert sorted(p.name for p in (tmp_path / ".gpucache/inductor/cache").iterdir()) == [
        "op0",
        "op1",
    ]
