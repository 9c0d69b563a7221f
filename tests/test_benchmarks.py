"""Benchmark helpers that decide what a table says, on fake clocks."""

from __future__ import annotations

import itertools
import subprocess
import sys

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


def test_rounds_below_one_are_refused_before_any_work():
    cmd = [sys.executable, "-m", "benchmarks.infer", "--rounds", "0", "--store", "/no/store.zarr"]
    r = subprocess.run(cmd, capture_output=True, text=True)
    assert r.returncode == 2
    assert r.stderr.strip().splitlines()[-1].endswith("--rounds must be at least 1, not 0")
