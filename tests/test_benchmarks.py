"""Benchmark helpers that decide what a table says (on fake clocks), the kernel plan, and the
CPU benchmarks that no other test runs."""

from __future__ import annotations

import itertools
import os
import re
import subprocess
import sys
import time

import numpy as np
import pytest

from benchmarks.infer import interleaved, rounds_table


def test_rounds_time_every_row_in_turn_and_the_table_reads_their_medians():
    calls, ticks = [], itertools.count(1)

    def clock(fn):
        calls.append(fn())
        return next(ticks) / 1000  # a machine that slows down as the run goes on

    rows = [("a", lambda: "a"), ("b", lambda: "b")]
    one = interleaved(rows, 3, clock)
    assert calls == ["a", "b"] * 3  # in turn, so the drift falls on both rows alike
    assert one == {"a": [0.001, 0.003, 0.005], "b": [0.002, 0.004, 0.006]}
    many = {"a": [0.02, 0.04, 0.03], "b": [0.01, 0.01, 0.05]}
    lines = rounds_table(one, many, batch=4).splitlines()
    assert lines[0].split() == ["mode", "ms/frame", "(b=1)", "range", "frames/s", "b=1", "ratio"]
    # medians: a 3 ms at b=1, 4 / 0.03 frames/s; b 4 ms, 4 / 0.01; ratios to the first row
    assert lines[1].split() == ["a", "3.000", "1.000-5.000", "133.3", "1.000"]
    assert lines[2].split() == ["b", "4.000", "2.000-6.000", "400.0", "1.333"]


def test_a_row_that_cannot_be_built_says_why_in_one_line_and_the_run_goes_on(capsys):
    from benchmarks.infer import built

    def fails():
        raise RuntimeError("cuDNN: no valid execution plan\n  (the details)")

    assert built("conv+ReLU", fails) is None
    assert built("plain", lambda: 7) == 7
    err = capsys.readouterr().err.splitlines()
    assert err == ["conv+ReLU: not built: RuntimeError: cuDNN: no valid execution plan"]


def test_the_profile_tells_apart_convolutions_that_differ_in_stride_alone():
    """``benchmarks.infer_profile``: an encoder convolution (stride 2) and a sub-pixel one
    (stride 1) of the same input and weight shapes get a FLOP count each, and the timed
    convolutions (``aten::convolution``) are found under the same keys."""
    import torch
    import torch.nn.functional as F
    from torch.profiler import ProfilerActivity, profile

    from benchmarks.infer_profile import conv_flops, conv_times

    w = torch.rand(16, 8, 3, 3)

    def net(x, light):
        return F.conv2d(x, w, None, 1, 1).sum() + F.conv2d(x, w, None, 2, 1).sum() + light

    x = torch.rand(2, 8, 32, 32)
    flops = conv_flops(net, x, torch.zeros(()))
    shapes = "[2, 8, 32, 32], [16, 8, 3, 3]"
    one = 2 * 2 * 16 * 32 * 32 * 8 * 9  # 2 x batch x out channels x out pixels x taps
    assert flops == {f"{shapes}, stride 1": one, f"{shapes}, stride 2": one / 4}
    with profile(activities=[ProfilerActivity.CPU], record_shapes=True) as prof:
        net(x, 0)
    assert conv_times(prof, forwards=1).keys() == flops.keys()


def test_the_profiles_flags_are_keywords_that_fast_network_takes():
    """``benchmarks.infer_profile.fast_kwargs``: every flag reaches ``fast_network`` under its
    own keyword (the profile only runs on CUDA, so a mistake here would cost a device call)."""
    import inspect

    from benchmarks.infer_profile import fast_kwargs, parser
    from trainer.rendering.infer import fast_network

    args = parser().parse_args(["--subpixel", "--edge-ring", "--conv-relu", "--light-sums",
                                "--fold-ring", "--align", "16"])  # fmt: skip
    fast = fast_kwargs(args)
    inspect.signature(fast_network).bind(None, compile=True, **fast)
    assert fast == {"subpixel": True, "align": 16, "edge_ring": True, "conv_relu": True,
                    "light_sums": True, "fold_ring": True}  # fmt: skip


def test_the_device_is_named_from_an_option_or_a_torch_device(monkeypatch):
    """``benchmarks.train.device_name``: the same name for ``--device``'s text and a torch
    device: the GPU's for CUDA (asked of torch, here stood in for), else the CPU's."""
    import torch

    from benchmarks.train import device_name

    monkeypatch.setattr(torch.cuda, "get_device_name", lambda *a: "the GPU")
    assert device_name("cuda") == device_name(torch.device("cuda")) == "the GPU"
    assert device_name("cpu") == device_name(torch.device("cpu"))
    assert device_name("cpu").startswith("CPU (")


def test_only_given_again_runs_the_rows_that_contain_any_of_its_texts():
    """``benchmarks.infer --only``: no text runs every row; one or more, the rows whose name
    contains any (a device call picks the rows it pays for)."""
    from types import SimpleNamespace

    from benchmarks.infer import Bench, parser

    def wanted(*argv):
        bench = SimpleNamespace(args=parser().parse_args(list(argv)))
        names = ["torch.compile + CUDA graph", "subpixel compiled + graph",
                 "subpixel compiled, zero-padded edge ring, conv+ReLU, light sums"]  # fmt: skip
        return [name for name in names if Bench.wanted(bench, name)]

    assert len(wanted()) == 3
    assert wanted("--only", "conv+ReLU") == ["subpixel compiled, zero-padded edge ring, "
                                             "conv+ReLU, light sums"]  # fmt: skip
    assert wanted("--only", "torch.compile", "--only", "conv+ReLU") == [
        "torch.compile + CUDA graph",
        "subpixel compiled, zero-padded edge ring, conv+ReLU, light sums",
    ]
    assert wanted("--only", "no such row") == []


def test_the_flags_ask_for_their_graph_rows_each_a_form_that_fast_network_takes():
    """``benchmarks.infer.graph_rows``: the CUDA rows each flag adds, in order, and keyword
    arguments that ``trainer.rendering.infer.fast_network`` binds (a mistake here would cost a
    device call: the rows only run on CUDA)."""
    import inspect

    from benchmarks.infer import graph_rows, parser
    from trainer.rendering.infer import FASTEST, fast_layers, fast_network

    plain = [name for name, _ in graph_rows(parser().parse_args([]))]
    assert plain == ["  + bf16 weights, CUDA graph", "subpixel bf16, CUDA graph"]
    every = ["--compile", "--zero-edge-ring", "--conv-relu", "--light-sums", "--fold-ring"]
    rows = graph_rows(parser().parse_args(every))
    assert [name for name, _ in rows][2:] == [
        "torch.compile + CUDA graph",
        "subpixel compiled + graph",
        "subpixel compiled, zero-padded edge ring",
        "subpixel compiled, zero-padded edge ring, conv+ReLU",
        "subpixel compiled, zero-padded edge ring, conv+ReLU, light sums",
        "subpixel compiled, zero-padded edge ring, conv+ReLU, light sums, ring in one product",
    ]
    signature = inspect.signature(fast_network)
    layers = inspect.signature(fast_layers)
    for _, fast in rows:  # each raises TypeError on a keyword it lacks
        signature.bind(None, **fast)
        layers.bind(None, **{k: v for k, v in fast.items() if k != "compile"})
    zero_relu = dict(rows)["subpixel compiled, zero-padded edge ring, conv+ReLU"]
    assert zero_relu == {"compile": True, "subpixel": True, "align": 8, "edge_ring": True,
                         "conv_relu": True}  # fmt: skip
    sums = dict(rows)["subpixel compiled, zero-padded edge ring, conv+ReLU, light sums"]
    assert sums == zero_relu | {"light_sums": True}
    assert rows[-1][1] == sums | {"fold_ring": True} == FASTEST | {"align": 8}
    alone = dict(graph_rows(parser().parse_args(["--fold-ring"])))
    name = "subpixel compiled, zero-padded edge ring, conv+ReLU, ring in one product"
    assert alone[name] == zero_relu | {"light_sums": False, "fold_ring": True}
    named = dict(graph_rows(parser().parse_args(["--align", "1", "--conv-relu"])))
    assert named["subpixel compiled, conv+ReLU, channels x1"]["align"] == 1
    assert not named["subpixel compiled, conv+ReLU, channels x1"]["edge_ring"]


def test_rounds_below_one_are_refused_before_any_work():
    cmd = [sys.executable, "-m", "benchmarks.infer", "--rounds", "0", "--store", "/no/store.zarr"]
    r = subprocess.run(cmd, capture_output=True, text=True)
    assert r.returncode == 2
    assert r.stderr.strip().splitlines()[-1].endswith("--rounds must be at least 1, not 0")


def test_kernel_plan_lists_the_launches_of_the_compiled_network_without_a_gpu():
    """benchmarks.kernel_plan: Inductor's Triton program for the sub-pixel network with edge
    rings on zero-padded phases and fused ReLUs, planned on this CPU: every convolution an
    extern launch (4 encoder, the bottleneck's 2, 4 sub-pixel and 3 skip convolutions; 5 of
    them with their ReLU, no pass of it left); each ring two
    gathers from its level's input (the taps along the edges, the corners) and two batched
    products; each level's sum, correction and activation one kernel, and no padded copy."""
    cmd = [sys.executable, "-m", "benchmarks.kernel_plan", "--subpixel", "--edge-ring"]
    cmd += ["--conv-relu", "--resolution", "32", "--width", "8", "--batch", "2"]
    r = subprocess.run(cmd, capture_output=True, text=True, timeout=600)
    assert r.returncode == 0, r.stderr[-2000:]
    names = [line.split()[1:3] for line in r.stdout.splitlines()[1:-1]]
    # with their ReLU in one operator: the encoder's 4 and the bottleneck's last
    assert names.count(["extern", "conv_relu"]) == 5
    assert names[:4] == [["extern", "conv_relu"]] * 4  # the encoder's: no pass between them
    assert names.count(["extern", "convolution"]) == 13 - 5
    assert names.count(["extern", "baddbmm"]) == names.count(["extern", "bmm"]) == 4
    fused = [n[0] for n in names if n[0].startswith("triton_")]
    assert sum("_index_" in n for n in fused) == 8
    levels = [n for n in fused if "pixel_shuffle" in n]
    assert len(levels) == 4 and "sigmoid" in levels[-1]  # the output level's, last
    assert not any("pad2d" in n for n in fused)  # no replicate padding pass
    assert r.stdout.splitlines()[-1].endswith("M elements in all")


def test_kernel_plan_parses_launches_and_refuses_edge_rings_without_the_rewrite(
    monkeypatch, capsys
):
    from benchmarks import kernel_plan
    from benchmarks.kernel_plan import launches

    source = (
        "def call(args):\n"
        "    buf0 = extern_kernels.convolution(arg0_1, arg1_1, stride=(1, 1))\n"
        "    triton_poi_fused_relu_0.run(buf0, buf1, 4096, stream=stream0)\n"
        "    triton_poi_fused_pad_1.run(buf1, buf2, 16, 256, stream=stream0)\n"
        "    extern_kernels.bmm(reinterpret_tensor(buf2, (4, 2), (2, 1), 0), arg2_1, out=buf3)\n"
    )
    assert launches(source) == [
        ("extern convolution", 0),
        ("triton_poi_fused_relu_0", 4096),
        ("triton_poi_fused_pad_1", 4096),
        ("extern bmm", 0),
    ]
    for extra, says in (
        (["--edge-ring"], "--edge-ring is a form of the --subpixel rewrite"),
        (["--conv-relu"], "--conv-relu is a form of the --subpixel rewrite"),
        (["--light-sums"], "--light-sums is a form of the --subpixel rewrite"),
        (["--subpixel", "--fold-ring"], "--fold-ring is a form of --edge-ring"),
    ):
        monkeypatch.setattr(sys, "argv", ["kernel_plan", *extra])
        with pytest.raises(SystemExit) as exit_:
            kernel_plan.main()
        err = capsys.readouterr().err.strip()
        assert exit_.value.code == 2 and err.endswith(says), err


def test_input_copy_times_copy_and_the_compiled_copy_after_checking_their_values():
    cmd = [sys.executable, "-m", "benchmarks.input_copy", "--batch", "1", "--resolution", "16"]
    r = subprocess.run([*cmd, "--iters", "2"], capture_output=True, text=True, timeout=600)
    assert r.returncode == 0, r.stderr[-2000:]
    rows = [line.split() for line in r.stdout.splitlines()[1:]]
    assert [row[0] for row in rows] == ["copy_", "Inductor-compiled"]
    assert all(float(row[1]) > 0 and row[2] == "ms" and float(row[3]) > 0 for row in rows)
    bad = subprocess.run([*cmd, "--iters", "0"], capture_output=True, text=True)
    assert bad.returncode == 2 and "must be positive" in bad.stderr


def test_the_training_rows_time_only_the_steps_after_the_warmup(capsys):
    """``benchmarks.train.print_table``: the trainer's images/s and data wait come from the
    log's windows after ``--warmup`` steps, each weighted by its seconds."""
    from benchmarks.train import parser, print_table

    args = parser().parse_args(["--steps", "6", "--warmup", "2"])
    log = [  # windows of 2 steps: the first is warm-up; then 8 images in 1 s, 8 in 3 s
        {"step": 2, "steps": 2, "images": 8, "images_per_second": 0.5, "data_wait": 0.9},
        {"step": 4, "steps": 2, "images": 8, "images_per_second": 8.0, "data_wait": 0.10},
        {"step": 6, "steps": 2, "images": 8, "images_per_second": 8 / 3, "data_wait": 0.02},
    ]
    ends = {True: (50.0, 0.25, 0.004)}
    print_table(args, 400.0, 9.0, ends, log)
    rows = capsys.readouterr().out.splitlines()
    assert rows[1].split() == ["loader", "only", "400.0", "-", "-"]
    assert rows[2].split()[-5:] == ["(trainer)", "50.0", "25.0%", "4", "ms"]
    assert "an iteration an epoch" not in "\n".join(rows)  # not measured: no row
    # 16 images in 4 s; wait (0.1 x 1 s + 0.02 x 3 s) / 4 s = 4 %
    assert rows[3].split() == ["train", "(steps", "3-6)", "4.00", "4.0%", "-"]


def test_the_materials_benchmark_reads_each_layout_and_refuses_a_tiny_texture():
    """``benchmarks.materials`` without Blender (``--no-render``) at 64²: a row for each
    layout with both readers' times and memory, read in fresh processes."""
    cmd = [sys.executable, "-m", "benchmarks.materials", "--texture", "64", "--repeat", "1",
           "--no-render"]  # fmt: skip
    r = subprocess.run(cmd, capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, r.stderr[-3000:]
    rows = re.findall(r"^\| ([^|]+) \| (\d+\.\d\d) / (\d+\.\d\d) \| (\d+) \| (\d+) / (\d+) \|",
                      r.stdout, re.M)  # fmt: skip
    assert [row[0] for row in rows] == ["5-panel PNG", "metal-rough folder (4 PNGs)",
                                        "the folder, all but the normal at half size"]  # fmt: skip
    assert all(int(row[4]) >= int(row[3]) > 0 for row in rows)  # peak at least the resident
    assert "texture swap" not in r.stdout  # no render worker asked for
    bad = subprocess.run([*cmd[:3], "--texture", "4"], capture_output=True, text=True)
    assert bad.returncode == 2 and "--texture must be at least 8" in bad.stderr


def test_worker_start_times_blender_in_a_ray_actor_both_ways_and_refuses_bad_counts():
    """``benchmarks.worker_start`` on the farm's embedded Ray: a row for each way of spawning
    Blender, and Ray in that Blender only where the parent's main script ran again."""
    cmd = [sys.executable, "-m", "benchmarks.worker_start", "--starts", "1", "--resolution", "16"]
    env = {**os.environ, "RAY_AUTH_MODE": "disabled"}
    r = subprocess.run(cmd, capture_output=True, text=True, timeout=300, env=env)
    assert r.returncode == 0, r.stderr[-2000:]
    rows = re.findall(r"^\| ([^|]+?) \| (\d+\.\d\d) \(\S+\) \| (\d+) \| (\w+) \|$", r.stdout, re.M)
    assert [(row[0].split(" (")[0], row[3]) for row in rows] == [
        ("RenderProcess", "no"),
        ("multiprocessing's default spawn", "yes"),
    ], r.stdout
    assert all(float(row[1]) > 0 and int(row[2]) > 0 for row in rows)
    bad = subprocess.run([*cmd[:3], "--starts", "0"], capture_output=True, text=True, timeout=60)
    assert bad.returncode == 2 and "--starts 0: must be at least 1" in bad.stderr


def test_the_learning_rows_pin_their_base_and_the_default_row_follows_the_trainer():
    """The ``shaderball`` row and every ``sb-*`` row keep their cues, batch, width and
    precision whatever the recipe's defaults are; ``default`` trains what ``trainer train``
    trains by default, which is ``sb-ambient-b4``'s settings at width 64; ``default-w32`` is
    ``sb-ambient-b4`` itself and ``default-fp32`` the default in fp32."""
    from benchmarks.learning import ROWS, SB
    from trainer.training.config import RECIPES, TrainConfig

    def config(name):
        return TrainConfig(store=("s",), **ROWS[name][1]).to_dict()

    default = config("default")
    assert default == TrainConfig(store=("s",)).to_dict()
    assert default == config("sb-ambient-b4") | {"width": 64, "precision": "auto"}
    assert config("default-w32") == config("sb-ambient-b4")
    assert config("default-fp32") == default | {"precision": "fp32"}
    base = config("shaderball")
    assert (base["batch_size"], tuple(base["inputs"])) == (8, SB["inputs"])
    assert base != config("default") and "ambient" in RECIPES["shaderball"]["inputs"]
    for name in (n for n in ROWS if n.startswith("sb-")):
        row = config(name)
        changed = {k for k in row if row[k] != base[k]}
        assert changed and changed <= {"batch_size", "lr", "inputs", "head", "loss", "width",
                                       "decoder_convs", "seed"}, (name, changed)  # fmt: skip
        assert set(row["inputs"]) >= set(base["inputs"]), name  # a cue added at most


def test_the_learning_rows_rates_scale_with_the_batch_given_to_every_row(capsys):
    """``--lr-scale``: each row's own rate times the batch ratio or its root; refused in one
    line without ``--batch``, before any store is read or rendered."""
    from benchmarks.learning import main, scaled_lr

    assert scaled_lr("shaderball", "-", 32, "linear") == pytest.approx(8e-3)
    assert scaled_lr("shaderball", "-", 32, "sqrt") == pytest.approx(4e-3)
    assert scaled_lr("sb-batch32-lr8e-3", "-", 32, "linear") == pytest.approx(8e-3)
    assert scaled_lr("paper", "-", 24, "none") == pytest.approx(1e-3)
    with pytest.raises(SystemExit) as stop:
        main(["--lr-scale", "linear", "--rows", "shaderball"])
    assert stop.value.code == 2
    assert "--lr-scale scales the rates to --batch: give --batch" in capsys.readouterr().err


def test_the_learning_rows_rate_rules_are_given_for_every_row_or_one(capsys):
    """``--lr-scale RULE`` for every row, ``ROW=RULE`` for one (the later wins; a row not
    trained is left alone), named in the table's note; a rule or row that is not one is
    refused in one line naming it."""
    from benchmarks.learning import main, said_rules, scale_rules
    from benchmarks.row_options import BadRowOption

    rows = ["default", "paper"]
    assert scale_rules([], rows) == {"default": "none", "paper": "none"}
    assert scale_rules(["sqrt", "paper=none"], rows) == {"default": "sqrt", "paper": "none"}
    assert scale_rules(["paper=linear", "sqrt"], rows) == {"default": "sqrt", "paper": "sqrt"}
    assert scale_rules(["sqrt", "paper=none"], ["default"]) == {"default": "sqrt"}
    assert said_rules({"default": "none", "paper": "none"}) == ""
    assert said_rules({"default": "sqrt", "paper": "sqrt"}) == (
        ", each row's rate scaled by the square root of the ratio of that batch to its own"
    )
    assert said_rules({"default": "sqrt", "paper": "none"}) == (
        ", the rate of default scaled by the square root of the ratio of that batch to its own"
        ", of paper not scaled")  # fmt: skip
    with pytest.raises(BadRowOption, match=r"^--lr-scale paper=cube: 'cube' is not one of none, "):
        scale_rules(["paper=cube"], rows)
    with pytest.raises(SystemExit) as stop:  # before any store is read or rendered
        main(["--rows", "default,paper", "--batch", "8", "--lr-scale", "papr=sqrt"])
    assert stop.value.code == 2
    assert "--lr-scale papr=sqrt: 'papr' is not a row (one of paper, " in capsys.readouterr().err


def test_the_learning_rows_share_a_calls_time_each_within_its_own_cap(capsys):
    """``--row-seconds`` caps a row (``SECONDS`` or ``ROW=SECONDS``); ``--seconds`` is the call's:
    a row trains within what is left of it, less the reserve for it and each row after it and
    the caps of those rows, so a row without a cap, trained last, takes the rest; a row left
    no time still trains a second. A cap that is no time or names no row is refused in one
    line before any store is read."""
    from benchmarks.learning import main
    from benchmarks.row_options import LEAST, RESERVE, BadRowOption, Schedule, per_row, seconds
    from benchmarks.row_options import time_limit as limit

    rows = ["paper", "default"]
    caps = per_row("--row-seconds", ["paper=200"], rows, ["paper", "default", "w32"], seconds)
    assert caps == {"paper": 200.0, "default": None}
    assert per_row("--row-seconds", ["30", "w32=5"], rows, ["paper", "default", "w32"],
                   seconds) == {"paper": 30.0, "default": 30.0}  # fmt: skip
    assert limit(200.0, [], None) == 200.0 and limit(None, [None], None) is None
    # 530 s left: the paper row keeps its cap, the default (last) gets what is left after it
    assert limit(200.0, [None], 530.0) == 200.0
    assert limit(None, [], 400.0) == 400.0 - RESERVE
    assert limit(200.0, [None], 250.0) == 250.0 - 2 * RESERVE  # less than its cap
    assert limit(None, [100.0], 530.0) == 530.0 - 2 * RESERVE - 100.0  # a later row's cap
    assert limit(None, [], 10.0) == LEAST
    clock = Schedule([(1, "paper"), (1, "default")], {(1, "paper"): 200.0, (1, "default"): None},
                     530.0, started=time.monotonic() - 100.0)  # fmt: skip
    assert clock.limit((1, "paper")) == 200.0
    assert 430.0 - RESERVE - 1.0 < clock.limit((1, "default")) <= 430.0 - RESERVE
    for value, said in (("paper=0", "'0' is not above 0"), ("paper=x", "'x' is not a number"),
                        ("papr=5", "'papr' is not a row")):  # fmt: skip
        with pytest.raises(BadRowOption, match=f"^--row-seconds {value}: {said}"):
            per_row("--row-seconds", [value], rows, ["paper", "default"], seconds)
    for argv, said in (
        (["--row-seconds", "paper=nan"], "--row-seconds paper=nan: 'nan' is not above 0"),
        (["--seconds", "0"], "--seconds must be above 0, not 0"),
    ):
        with pytest.raises(SystemExit) as stop:  # before any store is read or rendered
            main(["--rows", "default,paper", *argv])
        assert stop.value.code == 2 and said in capsys.readouterr().err


def test_a_learning_call_with_little_time_stops_its_row_there_and_says_so(
    tiny_store, tmp_path, capsys
):
    """``--seconds``: a call given less time than its row needs trains it within that time,
    scores it where it stopped, and says so in its log line and its table."""
    from benchmarks.learning import main
    from benchmarks.results import load

    argv = ["--store", tiny_store.url, "--rows", "paper", "--budget", "1000000", "--seconds",
            "1", "--grid-rows", "", "--work", str(tmp_path / "w"), "--results", str(tmp_path),
            "--name", "cut"]  # fmt: skip
    main(argv)
    out = capsys.readouterr().out
    assert "paper (1,000,000 passes" in out and "  stopped by its time limit at " in out
    # every figure of its table row, on one line (no interval: too few held-out materials)
    assert re.search(r"\n  [\d.]+ dB, SSIM 0\.\d+, FLIP 0\.\d+; \d+ steps, [\d,]+ passes", out)
    notes = load(tmp_path / "cut.json").notes
    assert any(n.startswith("paper: stopped by its time limit after ") for n in notes), notes


def test_a_learning_call_trains_every_row_in_the_precision_it_is_given(tiny_store, tmp_path):
    """``--precision``: every row's ``trainer train --precision``, over a row's own, and the
    table's precision column says what each trained in."""
    from benchmarks.learning import main
    from benchmarks.results import load

    for precision in ("bf16", "fp32"):
        main(["--store", tiny_store.url, "--rows", "paper,w32", "--budget", "6", "--grid-rows",
              "", "--precision", precision, "--work", str(tmp_path / precision), "--results",
              str(tmp_path), "--name", precision])  # fmt: skip
        rows = load(tmp_path / f"{precision}.json").rows
        assert [r[3] for r in rows] == [precision, precision]  # w32 pins fp32 of its own


def test_a_learning_row_stopped_by_its_time_limit_is_named_in_the_table_and_not_kept(
    tiny_store, tmp_path
):
    """A row stopped short of its budget by its time limit is scored where it stopped, the
    table says after how many passes, and it is not kept as done (the next call resumes). A
    row that ran all its steps is done though its epochs end in short batches."""
    from benchmarks import flops
    from benchmarks.learning import ROWS, run_row, table

    work = tmp_path / "work"
    cut = run_row("paper", tiny_store.url, work, 400, time_limit=1e-6, workers=0)
    assert cut["cut"] and cut["images"] == 6 and 5 < cut["psnr"] < 60  # one step of 6
    assert not (work / "400" / "paper" / "result.json").exists()
    said = "paper: stopped by its time limit after 6 of 400 passes, at a rate not yet annealed"
    assert said in table(32, 400, [cut], "about").notes
    # on a GPU the speed column is the training loop's passes a second, not per CPU-second
    on_gpu = table(32, 400, [cut], "about", device="cuda")
    assert on_gpu.columns[-2:] == ["passes / s", "TFLOP/s"]
    assert on_gpu.rows[0][-2] == round(cut["passes_per_second"], 1) > 0
    # and the work a second that speed is, from the FLOPs of one of the row's passes
    per_pass = flops.count(ROWS["paper"][1], 32)["pass"]
    assert on_gpu.rows[0][-1] == round(cut["passes_per_second"] * per_pass / 1e12, 1)
    # 21 training samples (7 materials x 3 suns) at batch 6: 4 steps train 6 + 6 + 6 + 3 passes
    full = run_row("paper", tiny_store.url, work, 21, workers=0)
    assert (full["steps"], full["images"]) == (4, 21) and "cut" not in full
    assert (work / "21" / "paper" / "result.json").exists()


def test_a_learning_budget_is_trained_in_the_fewest_whole_steps_that_reach_it():
    """``steps_for``: an epoch's last batch is short where the batch does not divide the
    split, so the steps for a budget of passes count whole epochs and then the rest."""
    from benchmarks.learning import steps_for

    assert steps_for(21, 6, 21) == 4  # 6 + 6 + 6 + 3
    assert steps_for(24, 6, 21) == 5  # an epoch, then 3 passes in a batch of 6
    assert steps_for(8, 6, 21) == 2 and steps_for(6, 6, 21) == 1 and steps_for(1, 6, 21) == 1
    assert steps_for(64_000, 4, 800) == 16_000  # a batch that divides the split: budget // batch
    # the GPU call's store: 2,125 training samples at batch 128, 17 steps (16 full) an epoch
    steps = steps_for(1_470_000, 128, 2125)
    epochs, rest = divmod(steps, 17)
    passes = epochs * 2125 + min(rest * 128, 2125)
    assert passes >= 1_470_000 > passes - 128 and steps > 1_470_000 // 128


@pytest.mark.slow
def test_the_learning_benchmark_trains_scores_and_tables_each_row_once(tiny_store, tmp_path):
    """``benchmarks.learning`` on the tiny real store: each row trained for the budget and
    scored on its held-out materials, the table written with the row's settings and the
    side-by-side grid drawn; run again, every row is read from its result, not trained.
    ``benchmarks.truth_noise`` then renders the held-out samples again (once) and tables the
    rows with and without the truth's noise, under its ceiling, with the noise's own FLIP."""
    import json

    from benchmarks.learning import precision_of
    from benchmarks.results import load
    from trainer.training.config import TrainConfig

    cmd = [sys.executable, "-m", "benchmarks.learning", "--store", tiny_store.url,
           "--budget", "8", "--rows", "paper,shaderball", "--work", str(tmp_path / "work"),
           "--results", str(tmp_path), "--name", "t"]  # fmt: skip
    r = subprocess.run(cmd, capture_output=True, text=True, timeout=600)
    assert r.returncode == 0, r.stderr[-3000:]
    table = load(tmp_path / "t.json")
    assert [row[0] for row in table.rows] == ["paper", "shaderball"]
    assert [row[2] for row in table.rows] == [6, 8]  # the recipes' batches
    assert [row[3] for row in table.rows] == [precision_of(TrainConfig(store=("-",))), "fp32"]
    assert all(5 < row[4] < 60 for row in table.rows)  # held-out PSNR dB
    assert table.command.startswith("python -m benchmarks.learning --store")
    assert (tmp_path / "t.png").stat().st_size > 0
    result = json.loads((tmp_path / "work" / "64" / "8" / "shaderball" / "result.json").read_text())
    assert result["images"] == 8 and result["passes_per_cpu_second"] > 0
    assert result["lr"] == 2e-3  # the recipe's own: no --lr-scale
    again = subprocess.run(cmd, capture_output=True, text=True, timeout=600)
    assert again.returncode == 0 and " steps of " not in again.stdout  # nothing trained again
    other = subprocess.run([*cmd, "--batch", "4", "--lr-scale", "linear"], capture_output=True,
                           text=True, timeout=600)  # fmt: skip
    assert other.returncode == 2 and " steps of " not in other.stdout
    assert ("paper was trained with batch_size=6, lr=0.001, not batch_size=4, "
            "lr=0.000666667: give another --work") in other.stderr  # fmt: skip
    done = tmp_path / "work" / "64" / "8" / "shaderball" / "result.json"
    done.rename(done.with_suffix(".kept"))  # a run left unfinished is checked too
    other = subprocess.run([*cmd, "--rows", "shaderball", "--batch", "4"], capture_output=True,
                           text=True, timeout=600)  # fmt: skip
    assert other.returncode == 2 and " steps of " not in other.stdout
    assert "shaderball was trained with batch_size=8, max_steps=1, not batch_size=4" in other.stderr
    done.with_suffix(".kept").rename(done)

    noise = [sys.executable, "-m", "benchmarks.truth_noise", *cmd[3:]]
    noise[noise.index("--name") + 1] = "n"
    r = subprocess.run(noise, capture_output=True, text=True, timeout=600)
    assert r.returncode == 0 and "render again" in r.stderr, r.stderr[-3000:]
    table = load(tmp_path / "n.json")
    ceiling = float(re.search(r"scores ([\d.]+) dB against the truth", table.notes[1]).group(1))
    assert [row[0] for row in table.rows] == ["paper", "shaderball"]
    assert all(row[1] <= row[2] and row[1] < ceiling for row in table.rows)
    noise_flip = float(re.search(r"LDR-FLIP ([\d.]+), the noise alone", table.notes[2]).group(1))
    assert 0 < noise_flip < 1
    r = subprocess.run(noise, capture_output=True, text=True, timeout=600)
    assert r.returncode == 0 and "render again" not in r.stderr  # the second renders are kept
    untrained = [("onecycle" if a == "paper,shaderball" else a) for a in noise]
    r = subprocess.run(untrained, capture_output=True, text=True, timeout=600)
    assert r.returncode == 2 and "onecycle is not trained: run benchmarks.learning" in r.stderr

    from benchmarks.store_renders import render_again
    from storage.reader import Store

    store = Store(tiny_store.url)  # the store's own seeds give the store's own renders
    spp = int(store.settings["samples"])
    same, seconds = render_again(store, [0, 1], spp, each_alone=True)
    assert np.allclose(same, [store.render(0), store.render(1)], atol=2e-3, rtol=2e-3)
    assert (seconds > 0).all()


def test_render_bits_tables_bytes_and_error_of_each_count_beside_the_renders_noise(
    tiny_store, tmp_path
):
    """Fewer bits: fewer bytes a render and a larger error, each within half a step of the
    bits kept; the second render's noise is larger than the rounding's at every count."""
    from benchmarks import render_bits
    from benchmarks.results import load
    from storage.schema import Layout
    from storage.writer import create_store

    render_bits.main(["--store", tiny_store.url, "--samples", "12", "--noise-samples", "3",
                      "--results", str(tmp_path), "--name", "b"])  # fmt: skip
    t = load(tmp_path / "b.json")
    bits = t.rows[:-1]
    assert [r[0] for r in bits] == [f"{b} bits" for b in render_bits.BITS]
    sizes, errors = [r[1] for r in bits], [float(r[3]) for r in bits]
    assert sizes == sorted(sizes, reverse=True) and sizes[-1] < sizes[0] and bits[0][2] == 1.0
    assert all(e <= 2.0 ** -(b + 1) for b, e in zip(render_bits.BITS, errors, strict=True))
    psnrs = [r[4] for r in bits[1:]]
    assert psnrs == sorted(psnrs, reverse=True) and bits[0][4] is None
    assert t.rows[-1][0].startswith("another ") and t.rows[-1][4] < psnrs[-1]
    rounded = create_store(str(tmp_path / "r.zarr"), Layout(2, 1, 16, 1), {"render_bits": 6})
    with pytest.raises(SystemExit) as stop:
        render_bits.main(["--store", rounded.url, "--results", str(tmp_path)])
    assert stop.value.code == 2


def test_the_cpu_training_forms_are_timed_in_turn_and_tabled(tmp_path):
    """``benchmarks.cpu_train`` at a tiny size: a row for each recipe and form asked for,
    positive rates, channels_last (the trainer's format) the unit of a recipe, the paper's
    step in each form the unit of that form.
    Inductor's form is left out: compiling two networks' training steps takes minutes on 2
    cores (the renderer's tests compile the network's operators)."""
    from benchmarks.results import load

    env = {**os.environ, "SHADERBALL_BENCH_RESULTS": str(tmp_path)}
    cmd = [sys.executable, "-m", "benchmarks.cpu_train", "--resolution", "16", "--batch", "2",
           "--rounds", "1", "--forms", "bf16 autocast,contiguous,one thread"]  # fmt: skip
    r = subprocess.run(cmd, capture_output=True, text=True, env=env, timeout=600)
    assert r.returncode == 0, r.stderr[-3000:]
    table = load(tmp_path / "cpu-train-16.json")
    forms = ["channels_last", "bf16 autocast", "contiguous", "one thread"]
    assert [(row[0], row[1], row[2]) for row in table.rows] == [
        (recipe, 2, form) for recipe in ("shaderball", "paper") for form in forms
    ]
    assert all(row[3] > 0 for row in table.rows) and table.rows[0][4] == 1.0
    assert [row[5] for row in table.rows[4:]] == [1.0] * 4  # the paper's: the unit of its form
    assert table.columns[4] == "x channels_last"


def test_the_viewer_benchmark_times_each_network_and_runtime_and_a_gallery(tmp_path):
    """``benchmarks.viewer`` at 16² on a layout Blender renders into ``--cache``: a row for
    each network and runtime with a frame made of its parts, and the gallery's rows."""
    from benchmarks.results import load

    env = {**os.environ, "SHADERBALL_BENCH_RESULTS": str(tmp_path)}
    common = [sys.executable, "-m", "benchmarks.viewer", "--resolutions", "16", "--frames", "2",
              "--texture", "32", "--device", "cpu", "--cache", str(tmp_path / "cache")]  # fmt: skip
    r = subprocess.run([*common, "--runtimes", "torch,onnx"], capture_output=True, text=True,
                       env=env, timeout=600)  # fmt: skip
    assert r.returncode == 0, r.stderr[-3000:]
    assert len(list((tmp_path / "cache").glob("screen_uv-16-*.npz"))) == 1
    table = load(tmp_path / "viewer-cpu.json")
    assert [(row[1], row[2]) for row in table.rows] == [
        (recipe, runtime) for recipe in ("shaderball", "paper") for runtime in ("torch", "onnx")
    ]
    for row in table.rows:
        mapping, network, encoding, frame = row[4:8]
        assert min(mapping, network, encoding) > 0 and frame > network, row
        assert 0 < float(row[8].rstrip(" %")) < 100, row
    r = subprocess.run([*common, "--library", "2"], capture_output=True, text=True, env=env,
                       timeout=600)  # fmt: skip
    assert r.returncode == 0, r.stderr[-3000:]
    assert re.search(r"^\| 2 \| \d+\.\d\d \| \d+\.\d\d \| [\d,]+ \| [\d,]+ \|$", r.stdout, re.M), (
        r.stdout
    )
    bad = subprocess.run([*common, "--runtimes", "graph"], capture_output=True, text=True)
    assert bad.returncode == 2 and "--runtimes graph runs on CUDA" in bad.stderr


def conv_and_linear_flops(model, *inputs) -> int:
    """FLOPs of ``model``'s convolutions and linear layers in one forward pass, counted from
    each layer's output shape (a multiply-add is two): a count apart from PyTorch's."""
    import torch
    from torch import nn

    total = 0

    def hook(module, _args, out):
        nonlocal total
        if isinstance(module, nn.Conv2d):
            k = module.kernel_size[0] * module.kernel_size[1]
            total += 2 * out.numel() * k * module.in_channels // module.groups
        else:
            total += 2 * out.numel() * module.in_features

    handles = [m.register_forward_hook(hook) for m in model.modules()
               if isinstance(m, nn.Conv2d | nn.Linear)]  # fmt: skip
    with torch.no_grad():
        model(*inputs)
    for h in handles:
        h.remove()
    return total


def test_pass_flops_counts_the_networks_layers_per_image_and_a_pass_about_thrice():
    import torch

    from benchmarks import flops
    from benchmarks.learning import ROWS

    for row in ("paper", "default"):
        counted = flops.count(ROWS[row][1], 32)
        model, _ = flops.network_and_loss(ROWS[row][1], 32)
        maps = torch.rand(1, model.config.in_channels, 32, 32)
        light = torch.rand(1, 4)
        cues = None if model.scene is None else model.scene(maps, light)
        assert counted["forward"] == conv_and_linear_flops(model, maps, light, cues)
        # the backward pass is about twice the forward (the first layer's input gradient is
        # not made); the loss is small beside both
        assert 2.8 < counted["pass"] / counted["forward"] < 3.1, counted
        assert counted["parameters"] == sum(p.numel() for p in model.parameters())
    paper = ROWS["paper"][1]
    four = flops.count(paper, 64)["forward"] / flops.count(paper, 32)["forward"]
    assert 3.9 < four < 4.01  # the work grows with the pixels (the light's MLP a little less)
    with pytest.raises(ValueError, match="needs VGG16 weights"):
        flops.count({"recipe": "paper"}, 32)  # the paper's own loss, L1 + VGG16
    r = subprocess.run([sys.executable, "-m", "benchmarks.pass_flops", "--rows", "paper,nope"],
                       capture_output=True, text=True)  # fmt: skip
    assert r.returncode == 2 and r.stderr.strip().splitlines()[-1].endswith(
        "--rows: nope: not a benchmarks.learning row"
    )


def test_a_flop_count_that_fails_leaves_the_gpu_tables_column_empty_not_the_table(
    monkeypatch, capsys
):
    from benchmarks import learning

    def broken(settings, resolution):
        raise RuntimeError("no counter here")

    monkeypatch.setattr(learning, "count", broken)
    result = {"row": "paper", "passes_per_second": 5000.0, "psnr": 30.0, "ssim": 0.9,
              "flip": 0.1, "batch": 128, "images": 1000, "steps": 8}  # fmt: skip
    t = learning.table(64, 1000, [result], "about", device="cuda")
    assert t.rows[0][-2:] == [5000.0, None]
    assert "paper: no TFLOP/s, the FLOP count failed (no counter here)" in capsys.readouterr().out
