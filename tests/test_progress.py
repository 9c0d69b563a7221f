"""The progress bars of every CLI: drawn on a terminal, whole lines in a log."""

from __future__ import annotations

import io

from shaderball import progress


class Terminal(io.StringIO):
    def isatty(self) -> bool:
        return True


def lines_of(every: float, monkeypatch, stream=None) -> str:
    """What a bar of 4 steps with a postfix and a line written between writes to ``stream``."""
    monkeypatch.setattr(progress, "PLAIN_EVERY", every)
    stream = io.StringIO() if stream is None else stream
    bar = progress.bar(total=4, desc="epoch 1/2", unit="step", file=stream)
    for i in range(4):
        bar.update(1)
        bar.set_postfix(loss=i)
        if i == 1:
            bar.write("a score", file=stream)
    bar.close()
    return stream.getvalue()


def test_a_bar_in_a_log_writes_whole_lines_with_its_figures(monkeypatch):
    text = lines_of(0.0, monkeypatch)
    assert "\r" not in text and text.endswith("\n")
    lines = text.splitlines()
    assert "a score" in lines and all(ln.strip() for ln in lines)  # no blank clearing lines
    bars = [ln for ln in lines if ln != "a score"]
    assert bars[0].startswith("epoch 1/2:   0%|") and "0/4" in bars[0]  # at once: no delay
    assert bars[1].startswith("epoch 1/2:  25%|") and "1/4" in bars[1]
    assert bars[-1].startswith("epoch 1/2: 100%|") and "4/4" in bars[-1]
    assert "loss=3" in bars[-1]  # the postfix rides with the next line


def test_a_bar_in_a_log_that_ends_within_the_interval_writes_nothing(monkeypatch):
    assert lines_of(3600.0, monkeypatch).splitlines() == ["a score"]


def test_a_bar_on_a_terminal_is_tqdms_own_and_a_disabled_one_writes_nothing(monkeypatch):
    drawn = lines_of(3600.0, monkeypatch, Terminal())
    assert "\r" in drawn and "100%" in drawn  # redrawn in place, whatever the interval
    monkeypatch.setattr(progress, "PLAIN_EVERY", 0.0)
    stream = io.StringIO()
    bar = progress.bar(range(3), disable=True, file=stream)
    assert list(bar) == [0, 1, 2] and stream.getvalue() == ""


def test_a_closed_stream_is_no_terminal():
    stream = io.StringIO()
    stream.close()
    assert not progress.on_terminal(stream)


def test_the_environment_sets_a_logs_interval(monkeypatch):
    monkeypatch.setenv(progress.EVERY_ENV, "0")
    assert progress.log_seconds() == 0.0
    assert "epoch 1/2:   0%|" in lines_of(3600.0, monkeypatch)  # the variable wins
    monkeypatch.setenv(progress.EVERY_ENV, "")
    assert progress.log_seconds() == progress.PLAIN_EVERY
