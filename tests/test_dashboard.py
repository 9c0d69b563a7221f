"""The farm dashboard: a real `farm dashboard` server over real stores; its security, its
metrics, and (slow) the pages in headless Chromium while a real farm job runs and is
cancelled from the page."""

from __future__ import annotations

import json
import os
import re
import socket
import subprocess
import time
import urllib.error
import urllib.request
from pathlib import Path

import pytest
from PIL import Image
from prometheus_client.parser import text_string_to_metric_families

from farm.state import JobState, WorkerStats, add_point
from shaderball.web import ICON_LINK, ICON_SVG
from storage.backend import Backend
from storage.schema import Layout, commit_key
from storage.writer import create_store, write_shard
from tests.conftest import s3_env
from tests.servers import ServerProcess
from tests.storage_helpers import synthetic_payload
from tests.test_farm import BIN, TINY, assert_exactly_once, farm, wait_for_commits

ARTIFACTS = Path(__file__).resolve().parent.parent / "test-artifacts"
LAYOUT = Layout(num_materials=6, suns_per_material=2, resolution=16, shard_size=4)


def synthetic_job(path: Path, committed=(0, 1), status="running", pending=()) -> JobState:
    """A store with some shards committed (and ``pending`` ones written but not committed, as
    a crash leaves them) and a job state as a driver leaves it."""
    store = create_store(str(path), LAYOUT, {"samples": 4, "sources": ["uniform:6"]})
    for shard in (*committed, *pending):
        write_shard(store, shard, synthetic_payload(LAYOUT, shard))
    for shard in pending:
        (path / commit_key(shard)).unlink()
    st = JobState(str(path), {}, LAYOUT.num_samples, LAYOUT.num_shards, status=status)
    st.frames_done = 4 * len(committed)
    st.frames_rendered = st.frames_done + 2  # and a result waiting for its shard
    st.shards_committed = len(committed)
    errors = [{"worker": "w1", "error": "boom", "at": 0}]
    st.failures = {"5": {"attempts": 2, "errors": errors, "final": True, "kind": "uniform",
                         "source": "uniform:seed=77"}}  # fmt: skip
    st.workers = {"w0": WorkerStats("w0", "busy", "vm", 10, frames=8, frame_seconds=4.0,
                                    last_seen=time.time()),
                  "w1": WorkerStats("w1", "dead", "vm", 11, failures=2)}  # fmt: skip
    st.started = time.time() - 100
    st.history = add_point(add_point([], time.time() - 90, 0), time.time() - 50, 4)
    st.save(Backend(str(path)))
    return st


class Server(ServerProcess):
    """``farm dashboard`` in a subprocess on a port of its own."""

    def __init__(self, *args, host="127.0.0.1", cwd=None):
        super().__init__([BIN / "farm", "dashboard", *args, "--host", host], "dashboard", cwd=cwd)

    def get(self, path: str, headers: dict | None = None, method="GET") -> tuple[int, bytes]:
        req = urllib.request.Request(self.base + path, headers=headers or {}, method=method)
        try:
            with urllib.request.urlopen(req, timeout=30) as r:
                return r.status, r.read()
        except urllib.error.HTTPError as e:
            return e.code, e.read()


def raw_get(port: int, path: str) -> int:
    """A request sent with its path exactly as given (no client-side normalising)."""
    import http.client

    c = http.client.HTTPConnection("127.0.0.1", port, timeout=10)
    c.request("GET", path)
    return c.getresponse().status


@pytest.fixture(scope="module")
def sets(tmp_path_factory) -> Path:
    root = tmp_path_factory.mktemp("sets")
    synthetic_job(root / "a.zarr", pending=(2,))
    (root / "broken.zarr").mkdir()
    (root / "broken.zarr" / "zarr.json").write_text("{not json")
    secret = tmp_path_factory.mktemp("outside")
    (secret / "zarr.json").write_text("{}")
    os.symlink(secret, root / "escape")
    return root


def test_pages_errors_and_paths_that_leave_the_roots(sets, tmp_path):
    for run in ("runs/kept", "away"):  # a run folder, and a link in it to one outside it
        (tmp_path / run).mkdir(parents=True)
        (tmp_path / run / "config.json").write_text("{}")
        (tmp_path / run / "eval.png").write_bytes(b"\x89PNG")
    os.symlink(tmp_path / "away", tmp_path / "runs" / "away")
    stopped = synthetic_job(tmp_path / "stopped.zarr", status="failed")
    stopped.stop_error = "no live worker for 300 s: Ray could not place a worker needing ..."
    stopped.workers["w2"] = WorkerStats("w2", "starting")
    stopped.save(Backend(str(tmp_path / "stopped.zarr")))
    growing = synthetic_job(tmp_path / "growing.zarr")
    growing.workers["w2"] = WorkerStats("w2", "starting")  # Ray has not placed it yet
    growing.save(Backend(str(tmp_path / "growing.zarr")))
    roots = (tmp_path / "stopped.zarr", tmp_path / "growing.zarr")
    with Server(sets, *roots, "--runs", tmp_path / "runs") as s:
        code, body = s.get("/runs")
        assert code == 200 and b"runs/kept <small>" in body and b"away" not in body
        page = s.get("/job/1")[1].decode()  # a failed job says why it stopped
        assert '<p class="err" id="stop-error">stopped: no live worker for 300 s' in page
        assert 'id="waiting"' not in page  # a stopped job waits for nothing
        assert 'id="fps-now"' not in page  # nor has a rate of now
        assert '<small id="waiting"> +1 starting</small>' in s.get("/job/2")[1].decode()
        code, body = s.get("/")
        page = body.decode()
        assert code == 200 and f'href="/job/0/a.zarr">{sets}/a.zarr</a>' in page  # as given
        assert "broken.zarr" in page and "not valid JSON" in page  # an error row, a page
        # a running job's rate of the last window (its ETA's) beside the run's mean
        assert re.search(r'<td class="num">[0-9.]+\s*<small title="[^"]*">\s*\([0-9.]+ now\)', page)
        code, body = s.get("/job/0/a.zarr")
        assert f"<title>{sets}/a.zarr - shaderball</title>".encode() in body
        assert ICON_LINK.encode() in body
        for icon in ("/favicon.svg", "/favicon.ico"):  # the link's, and browsers' own guess
            assert s.get(icon) == (200, ICON_SVG.encode())
        assert re.search(rb'<small id="fps-now"> [0-9.]+ in the last\s+30 s</small>', body)
        assert code == 200 and b"shardmap" in body and b"boom" in body and b"(stale)" not in body
        assert b"uniform:seed=77" in body  # the failed material's source
        assert b"committed 2" in body and b"pending 1" in body  # the shard map's legend
        assert s.get("/thumb/0/a.zarr?sample=0")[1][:4] == b"\x89PNG"
        assert s.get("/sheet/0/a.zarr?sample=5")[1][:4] == b"\x89PNG"
        assert s.get("/thumb/0/a.zarr?sample=9")[0] == 404  # shard 2 is not committed
        for path in ("/job/0/../../etc", "/job/0/%2e%2e/%2e%2e/etc", "/job/0/%2E%2E%2Fx",
                     "/job/0//etc", "/job/0/escape", "/job/7/a.zarr", "/thumb/0/escape?sample=0",
                     "/runfile/0/..?file=eval.png", "/job/0/..%2f..%2fetc",
                     "/runfile/0/away?file=eval.png"):  # fmt: skip
            assert raw_get(s.port, path) in (400, 404), path
        # a POST needs the page's secret: another site's form cannot cancel a job
        assert s.get("/cancel/0/a.zarr", method="POST")[0] == 403
        # a page from a domain rebound to 127.0.0.1 is refused (no token: loopback names only)
        assert s.get("/", {"Host": "evil.example:8266"})[0] == 403
        assert s.get("/", {"Host": f"localhost:{s.port}"})[0] == 200


def test_an_empty_jobs_page_says_where_it_looked_and_what_it_filtered(tmp_path):
    (tmp_path / "empty").mkdir()
    with Server(tmp_path / "empty", tmp_path / "later") as s:
        code, page = s.get("/")
        roots = f"{tmp_path / 'empty'}, {tmp_path / 'later'}"
        assert code == 200 and f"No stores found under\n{roots}." in page.decode()
        assert b"No jobs match the filter: failed." in s.get("/?status=failed")[1]


def test_a_non_loopback_host_needs_a_token(sets):
    with Server(sets, host="0.0.0.0") as s:
        deadline = time.time() + 10
        while time.time() < deadline and s.get("/")[0] != 401:
            time.sleep(0.2)
        assert s.get("/")[0] == 401 and s.get("/metrics")[0] == 401
        assert s.get("/job/0/a.zarr?token=wrong")[0] == 401
        out, _ = s.stop()
    token = out.split("token (needed by every request from another machine): ")[1].split()[0]
    with Server(sets, "--token", token, host="0.0.0.0") as s:
        assert s.get(f"/?token={token}")[0] == 200
        assert s.get("/", {"Authorization": f"Bearer {token}"})[0] == 200
        assert s.get("/")[0] == 401


def test_a_taken_port_or_an_unknown_host_is_one_line(tmp_path):
    """Both servers listen through ``shaderball.web.serve``: the address is named, nothing runs."""
    dashboard = [str(BIN / "farm"), "dashboard", str(tmp_path)]
    with socket.socket() as taken:
        taken.bind(("127.0.0.1", 0))
        taken.listen()
        port = taken.getsockname()[1]
        r = subprocess.run([*dashboard, "--port", str(port)], capture_output=True, text=True)
    assert r.returncode == 1 and r.stdout == ""
    assert r.stderr == (
        f"Error: cannot listen on 127.0.0.1:{port}: Address already in use "
        "(another --port, or 0 for any free one)\n"
    )
    bad_host = [*dashboard, "--host", "no-such-host.invalid", "--token", "t"]
    r = subprocess.run(bad_host, capture_output=True, text=True)
    assert r.returncode == 1 and len(r.stderr.splitlines()) == 1
    assert r.stderr.startswith("Error: cannot listen on --host no-such-host.invalid: ")
    missing = [*dashboard[:2], str(tmp_path / "typo"), "--runs", str(tmp_path / "runs")]
    with socket.socket() as taken:  # a root and a runs folder not there: said, not refused
        taken.bind(("127.0.0.1", 0))
        taken.listen()
        port = taken.getsockname()[1]
        r = subprocess.run([*missing, "--port", str(port)], capture_output=True, text=True)
    assert r.stderr.splitlines() == [
        f"warning: {tmp_path / 'typo'} does not exist (yet): shown once it is written",
        f"warning: {tmp_path / 'runs'} does not exist (yet): shown once it is written",
        f"Error: cannot listen on 127.0.0.1:{port}: Address already in use "
        "(another --port, or 0 for any free one)",
    ]


def test_metrics_parse_and_match_the_job_state(sets, tmp_path):
    runs = tmp_path / "runs" / "r1"
    runs.mkdir(parents=True)
    lines = [
        {"step": s, "epoch": 0, "loss": 1 / s, "images_per_second": 50.0, "data_wait": 0.01,
         "time": time.time()}
        for s in (10, 20)
    ]  # fmt: skip
    (runs / "log.jsonl").write_text("\n".join(json.dumps(x) for x in lines))
    scores = [{"step": s, "epoch": 0, "samples": 4, "psnr": p, "ssim": 0.5, "heldout_set": "3f2a"}
              for s, p in ((10, 21.5), (20, 23.25), (30, 22.0))]  # fmt: skip
    sure = [  # r1's scores say how sure they are: an interval, and the move from the best
        {**x, "materials": 6, "psnr_low": x["psnr"] - 0.5, "psnr_high": x["psnr"] + 0.5}
        for x in scores
    ]
    sure[1]["vs_best"] = {"step": 10, "mean": 1.75, "low": 1.25, "high": 2.25}
    sure[2]["vs_best"] = {"step": 20, "mean": -1.25, "low": -1.5, "high": -1.0}
    (runs / "val.jsonl").write_text("\n".join(json.dumps(x) for x in sure) + "\n{torn")
    Image.new("RGB", (8, 8), (200, 30, 30)).save(runs / "val.png")
    other = tmp_path / "runs" / "r2"  # a second scored run: the page compares the two
    init = runs / "checkpoints" / "step-00000030.pt"  # r2 is fine-tuned from r1's
    other.mkdir()
    config = {"store": ["/data/set.zarr"], "loss": "l1", "lr": 0.001, "lr_schedule": "constant",
              "ema_decay": 0.0, "max_steps": None}  # fmt: skip
    (runs / "config.json").write_text(json.dumps(config))
    (other / "config.json").write_text(
        json.dumps({**config, "lr_schedule": "cosine", "ema_decay": 0.999, "init": str(init)})
    )
    averaged = [{**x, "psnr": x["psnr"] - 1, "trained_psnr": x["psnr"] - 3} for x in scores]
    (other / "val.jsonl").write_text(  # an averaged run: its trained weights are scored too
        "\n".join(json.dumps(x) for x in averaged)
    )
    overall = {"n": 50, "psnr": 24.5, "ssim": 0.8, "flip": 0.2}  # trainer eval's eval.json
    interval = {"materials": 10, "psnr_low": 23.75, "psnr_high": 25.25}
    (runs / "eval.json").write_text(json.dumps({"checkpoint_step": 30,
                                                "overall": {**overall, **interval}}))  # fmt: skip
    (other / "eval.json").write_text(json.dumps({"checkpoint_step": 30, "overall": overall}))
    for run in (runs, other):  # listed, not read
        (run / "checkpoints").mkdir()
        (run / "checkpoints" / "step-00000030.pt").write_bytes(b"")
    with Server(sets, "--runs", tmp_path / "runs") as s:
        code, body = s.get("/metrics")
        families = {f.name: f for f in text_string_to_metric_families(body.decode())}
        runs_page = s.get("/runs")[1].decode()
        grid = s.get("/runfile/0/r1?file=val.png")
        nothing = s.get("/runfile/0/r1?file=config.json")
        (other / "val.jsonl").write_text(  # the same run scoring other held-out samples
            "\n".join(json.dumps({**x, "heldout_set": "9b1c"}) for x in averaged)
        )
        mixed_page = s.get("/runs")[1].decode()
    assert code == 200
    value = {
        (x.name, tuple(sorted(x.labels.items()))): x.value
        for f in families.values()
        for x in f.samples
    }
    store = (("store", f"{sets}/a.zarr"),)  # the root as given, then the store's path
    assert value[("shaderball_farm_frames_committed_total", store)] == 8
    assert value[("shaderball_farm_frames_rendered_total", store)] == 10
    assert value[("shaderball_farm_frames_planned", store)] == 12
    assert value[("shaderball_farm_failures_total", store)] == 2
    assert value[("shaderball_farm_materials_failed", store)] == 1
    assert value[("shaderball_farm_workers", (("status", "busy"), *store))] == 1
    assert value[("shaderball_farm_shards_committed_total", store)] == 2
    assert value[("shaderball_farm_frame_seconds_count", store)] == 8
    run = (("run", f"{tmp_path / 'runs'}/r1"),)
    assert value[("shaderball_train_step", run)] == 20
    assert value[("shaderball_train_loss", run)] == pytest.approx(0.05)
    assert value[("shaderball_train_val_psnr_db", run)] == 22.0  # the last score, not the best
    assert value[("shaderball_train_val_ssim", run)] == 0.5
    assert value[("shaderball_train_val_psnr_low_db", run)] == 21.5  # the last score's interval
    assert value[("shaderball_train_val_psnr_high_db", run)] == 22.5
    averaged = (("run", f"{tmp_path / 'runs'}/r2"),)
    assert value[("shaderball_train_val_trained_psnr_db", averaged)] == 19.0
    assert ("shaderball_train_val_trained_psnr_db", run) not in value
    assert "held-out PSNR<b>22.00 dB" in runs_page  # a torn last line is skipped
    assert "<small>[21.50, 22.50] over\n6 materials</small>" in runs_page
    assert "-1.25 dB [-1.50, -1.00] on step 20's, the best\nbefore" in runs_page
    assert "best 23.25 dB at step 20" in runs_page and "steps 10 to 30" in runs_page
    # the PSNR curve spans its own range with its interval's band, not from 0
    assert '">21</text>' in runs_page and runs_page.count('<polygon class="band"') == 1
    assert "held-out samples at step 30" in runs_page and "file=val.png" in runs_page
    assert grid[0] == 200 and grid[1][:4] == b"\x89PNG" and nothing[0] == 404
    compare = runs_page[runs_page.index("Held-out PSNR of every run") :]
    assert compare.index(f"{tmp_path / 'runs'}/r1") < compare.index(f"{tmp_path / 'runs'}/r2")
    assert '">20.5</text>' in compare and compare.count("<polyline") >= 2
    assert not any("material=" in str(k) for k in value)  # never a material label
    assert f"{tmp_path / 'runs'}/r1 <small>" in runs_page and "<svg" in runs_page
    # the averaged run's held-out chart has the trained weights' line, and a card of its own
    i1, i2 = (runs_page.index(f"{tmp_path / 'runs'}/{r} <small>") for r in ("r1", "r2"))
    r1, r2 = runs_page[i1:i2], runs_page[i2:]
    assert "trained weights" not in r1 and r1.count("<polyline") == 4
    eval_line = re.sub(r"\s+", " ", re.sub(r"<[^>]+>", "", r1[r1.index("eval at step") :]))
    assert eval_line.startswith("eval at step 30: PSNR 24.50 dB [23.75, 25.25], SSIM 0.8000 on 50 "
                                "held-out samples of 10 materials")  # fmt: skip
    eval_line = re.sub(r"\s+", " ", re.sub(r"<[^>]+>", "", r2[r2.index("eval at step") :]))
    line = "eval at step 30: PSNR 24.50 dB, SSIM 0.8000 on 50 held-out samples"  # no interval
    assert eval_line.startswith(line) and not eval_line[len(line) :].startswith(" of")
    assert "trained weights' PSNR<b>19.00 dB</b>" in r2 and r2.count("<polyline") == 2
    assert "moving average (renders)" in r2 and '">18.5</text>' in r2  # both lines' range
    # each run's settings, and a table of those that differ between the runs
    assert "stores <b>set.zarr</b> · loss <b>l1</b> · lr <b>0.001</b>" in runs_page
    assert "weight average <b>-</b> · max steps <b>-</b>" in runs_page  # none, as the run says
    start = compare.index("Settings that differ")
    differ = compare[start : compare.index("<h2>", start)]
    heads = re.findall(r"<th>([^<]*)</th>", differ)
    assert heads == ["run", "fine-tuned from", "schedule", "weight average"]
    assert re.findall(r"<td>([^<]*)</td>", differ) == [
        f"{tmp_path / 'runs'}/r1", "-", "constant", "-",
        f"{tmp_path / 'runs'}/r2", "r1/step-00000030.pt", "cosine", "0.999",
    ]  # fmt: skip
    # runs that score other held-out samples are flagged, and the table names their samples
    assert 'id="mixed"' not in runs_page and 'id="mixed"' in mixed_page
    start = mixed_page.index("Settings that differ")
    differ = mixed_page[start : mixed_page.index("<h2>", start)]
    assert re.findall(r"<th>([^<]*)</th>", differ)[-1] == "held-out samples"
    assert re.findall(r"<td>([^<]*)</td>", differ)[4::5] == ["3f2a", "9b1c"]
    # runs of the same samples get the command that compares them sample by sample
    command = f"trainer eval --checkpoint {runs} --checkpoint {other}"
    assert f"<code>{command}</code>" in runs_page and "compare-command" not in mixed_page
    # a fine-tuned run gets the commands that compare it with the network it starts from
    gained = f"trainer eval --checkpoint {other} --checkpoint {init}"
    forgot = f"trainer eval --checkpoint {init} --checkpoint {other}"
    assert f"<code>{gained}</code>" in mixed_page and f"<code>{forgot}</code>" in mixed_page
    assert mixed_page.count('class="tuned-command"') == 1


@pytest.mark.slow
def test_the_job_page_in_chromium_follows_a_running_job_and_cancels_it(tmp_path):
    from playwright.sync_api import sync_playwright

    out, hold = tmp_path / "out" / "live.zarr", tmp_path / "hold"
    args = ["submit", "-m", "uniform:30", *TINY, "--workers", "2", "-o", out]
    hold.touch()  # the last 5 shards wait until the cancel: the job cannot end before it
    held = {"while": str(hold), "materials": list(range(20, 30))}
    job = farm(*args, faults={"slow_s": 2.0, "hold_materials": held}, wait=False)
    try:
        wait_for_commits(out, 1)
        with Server("out", cwd=tmp_path) as s, sync_playwright() as p:  # as the README runs it
            browser = p.chromium.launch(executable_path=chromium(), args=["--no-sandbox"])
            page = browser.new_page(viewport={"width": 1200, "height": 900})
            failed = []
            page.on("console", lambda m: m.type == "error" and failed.append(m.text))
            page.goto(s.base + "/")
            row = page.locator("#jobs tr", has_text="live.zarr")
            assert "running" in row.inner_text()
            page.goto(s.base + "/job/0/live.zarr")
            assert page.locator("#live h2").first.inner_text().startswith("out/live.zarr running")
            first = page.locator("#frames").inner_text()
            page.wait_for_function(  # the page refreshes itself as the job goes on
                f"document.getElementById('frames').textContent.trim() !== '{first}'",
                timeout=60_000,
            )
            page.wait_for_selector("svg.chart", timeout=30_000)
            page.wait_for_function(
                "[...document.querySelectorAll('#thumbs img')].some(i => i.naturalWidth > 0)"
            )
            done, total = page.locator("#frames").inner_text().split("/")  # read before the
            status = json.loads(farm("status", out, "--json").stdout)  # state it cannot pass
            assert int(total) == status["frames_total"]
            assert int(done) <= status["frames_done"] + status["frames_skipped"]
            ARTIFACTS.mkdir(exist_ok=True)
            page.screenshot(path=str(ARTIFACTS / "dashboard-job.png"), full_page=True)
            assert not failed, failed  # every request answered, the tab's icon included
            page.on("dialog", lambda d: d.accept())
            page.click("button:has-text('cancel')")
            page.wait_for_function(  # a refresh shows the request, the button gone
                "document.getElementById('cancel-msg').textContent.includes('requested by') && "
                "!document.querySelector('#live button')"
            )
            page.screenshot(path=str(ARTIFACTS / "dashboard-job-cancel.png"))
            hold.unlink()  # the tasks in flight end; those not started are dropped
            stdout, stderr = job.communicate(timeout=120)
            assert job.returncode == 0, stderr[-2000:]
            assert "cancelled" in stdout
            page.wait_for_function(  # the page sees the end by itself
                "document.querySelector('#live .s-cancelled') !== null", timeout=30_000
            )
            final = json.loads(farm("status", out, "--json").stdout)
            done, total = page.locator("#frames").inner_text().split("/")
            assert int(done) == final["frames_done"] + final["frames_skipped"] < int(total)
            browser.close()
    finally:
        job.kill()
    assert final["status"] == "cancelled"
    r = farm(*args)  # the same command resumes and completes it
    assert r.returncode == 0, r.stderr[-2000:]
    assert "resuming:" in r.stdout
    assert_exactly_once(out, 30)


def chromium() -> str:
    """Debian's Chromium (the test command installs it); fail in one line without it."""
    for path in ("/usr/bin/chromium", "/usr/bin/chromium-browser"):
        if Path(path).exists():
            return path
    pytest.fail("no Chromium at /usr/bin/chromium: run `make test`, which installs it", False)


def test_the_progress_history_stays_bounded_over_a_long_job():
    history: list = []
    for k in range(10_000):
        history = add_point(history, float(k), k * 5, limit=100)
    assert len(history) <= 100
    assert history[0] == [0.0, 0] and history[-1] == [9999.0, 49995]
    times = [t for t, _ in history]
    assert times == sorted(times) and times[len(times) // 2] > 2000  # spread over the life


def test_the_frames_per_second_chart_follows_renders_not_the_steps_of_commits():
    """Points every 2 s of a job rendering a material (5 frames) every 4 s and committing a
    shard of 20 frames every 16 s: every rate after the first window reads 1.25 frames/s
    within a material's worth over the window, never the zeros and jumps of commits."""
    from farm.dashboard.jobs import rates
    from farm.state import RATE_WINDOW_S

    history: list = []
    for k in range(61):
        t = 2.0 * k
        history = add_point(history, t, 20 * int(t // 16), 5 * int(t // 4))
    chart = rates(history)
    assert [t for t, _ in chart] == [2.0 * k for k in range(1, 61)]
    settled = [r for t, r in chart if t >= RATE_WINDOW_S + 2]
    assert settled and all(abs(r - 1.25) <= 5 / RATE_WINDOW_S for r in settled), settled
    # a state of committed frames only (two values a point) is read the same way
    old = rates([[0.0, 0], [10.0, 20], [40.0, 20], [100.0, 60]])
    assert old == [(10.0, 2.0), (40.0, 0.0), (100.0, 40 / 60)]
    # a history halved to points further apart than the window: consecutive points
    assert rates([[0.0, 0, 0], [100.0, 80, 100], [300.0, 80, 300]]) == [(100.0, 1.0), (300.0, 1.0)]


def test_the_eta_follows_the_rate_of_the_last_window_as_a_cluster_grows():
    """1 frame/s for 60 s, then 4 (nodes added): the time left is the frames left at 4 a
    second, where the run's mean (1.5) would say 2.7x that; with nothing rendered in the
    last window (commits still to come) it falls back to the mean."""
    st = JobState("s", {}, frames_total=1000, shards_total=40, started=0.0)
    st.history = [[t, 0, t] for t in range(0, 62, 2)]
    st.history += [[t, 0, 60 + 4 * (t - 60)] for t in range(62, 92, 2)]
    st.updated, st.frames_done = 90.0, 100
    data = json.loads(st.to_json())
    assert data["frames_per_s_now"] == pytest.approx(4.0)
    assert data["eta_s"] == pytest.approx(900 / 4.0) and data["frames_per_s"] == pytest.approx(
        100 / 90
    )
    st.history += [[t, 100, 180] for t in range(92, 130, 2)]
    st.updated = 128.0
    data = json.loads(st.to_json())
    assert data["frames_per_s_now"] == 0.0 and data["eta_s"] == pytest.approx(900 / (100 / 128))


def test_the_compare_commands_name_runs_of_the_same_samples_that_have_checkpoints(
    tmp_path, monkeypatch
):
    from farm.dashboard.runs import HELDOUT, compare_commands, finetune_commands, run_summary

    def run(path, held="3f2a", ckpts=("step-1.pt",), val=({"psnr": 1},)):
        return {"path": path, "label": path.upper(), "settings": {HELDOUT: held} if held else {},
                "checkpoints": list(ckpts), "val": list(val)}  # fmt: skip

    unscored = run("c", val=())  # left out: nothing to compare it on
    assert compare_commands([run("a"), run("b d"), unscored]) == [
        {"labels": ["A", "B D"], "command": "trainer eval --checkpoint a --checkpoint 'b d'"}
    ]
    for other in (run("b", held="9b1c"), run("b", held=None), run("b", ckpts=())):
        assert compare_commands([run("a"), other]) == []
    assert compare_commands([run("a"), unscored]) == []
    # each set of runs that score the same samples gets its own command, in page order
    mixed = [run("a"), run("x", held="9b1c"), run("b"), run("y", held="9b1c"), run("z", "77")]
    assert [c["command"] for c in compare_commands(mixed)] == [
        "trainer eval --checkpoint a --checkpoint b",
        "trainer eval --checkpoint x --checkpoint y",
    ]
    tuned = {**run("t"), "init": str(tmp_path), "label": "t"}
    assert finetune_commands([run("a"), tuned]) == [{
        "label": "t",
        "gained": f"trainer eval --checkpoint t --checkpoint {tmp_path}",
        "forgot": f"trainer eval --checkpoint {tmp_path} --checkpoint t",
    }]  # fmt: skip
    for gone in ({"init": str(tmp_path / "gone")}, {"val": []}, {"checkpoints": []}):
        assert finetune_commands([{**tuned, **gone}]) == []
    monkeypatch.chdir(tmp_path)  # a dashboard given --runs relative names its runs absolutely
    assert run_summary("0/a", Path("runs/a"))["path"] == str(tmp_path / "runs" / "a")


def test_store_settings_show_as_people_read_them():
    from farm.dashboard import pages

    page = pages.ENV.from_string("{% for v in values %}[{{ v|setting }}]{% endfor %}").render(
        values=[None, False, True, 256, "HOSEK_WILKIE", {"lens_mm": 50.0}, [2.0, 10.0]]
    )
    assert page == "[-][no][yes][256][HOSEK_WILKIE][{&#34;lens_mm&#34;: 50.0}][[2.0, 10.0]]"
    numbers = pages.ENV.from_string('{{ a|num("%.1f %%", 100) }} {{ b|num("%.4f") }}')
    assert numbers.render(a=0.0123, b=None) == "1.2 % -"


def test_a_chart_of_one_point_shows_the_value_and_where_it_was_taken():
    from farm.dashboard import pages

    assert pages.line_chart([]) == "<p>no progress points yet</p>"
    one = pages.line_chart([(6, 0.143717)], steps=True)  # a run of one log line
    assert one == '<p class="one-point">one point so far: <b>0.1437</b> at step 6</p>'
    assert "at 12 s" in pages.line_chart([(12.2, 0.7)])
    assert pages.line_chart([(0, 1.0), (5, 2.0)]).startswith("<svg")


def test_farm_cancel_asks_a_running_job_and_refuses_others(tmp_path):
    from farm.dashboard import pages
    from farm.dashboard.app import Dashboard

    synthetic_job(tmp_path / "run.zarr")
    synthetic_job(tmp_path / "done.zarr", status="done")
    dash = Dashboard([str(tmp_path)], [])
    assert "cancelJob(" in pages.render("job_live", **dash.job_context("0/run.zarr"))
    r = farm("cancel", tmp_path / "run.zarr")
    assert r.returncode == 0 and "cancel requested" in r.stdout
    by = json.loads((tmp_path / "run.zarr" / "farm" / "cancel.json").read_text())["by"]
    # the page's refreshes keep saying so, and offer no second cancel, until the job stops
    fragment = pages.render("job_live", **dash.job_context("0/run.zarr"))
    assert re.search(f'<span id="cancel-msg">cancel requested by\\s+{re.escape(by)} at ', fragment)
    assert "cancelJob(" not in fragment
    status = farm("status", tmp_path / "run.zarr").stdout  # and so does `farm status`
    said = r"^cancel    requested by farm cancel \d+ s ago: the driver stops within"
    assert re.search(said, status, re.M), status
    r = farm("cancel", tmp_path / "done.zarr")
    assert r.returncode == 1 and r.stderr.strip() == (
        f"Error: {tmp_path / 'done.zarr'}: the job is done, not running"
    )
    assert not (tmp_path / "done.zarr" / "farm" / "cancel.json").exists()


def test_an_s3_prefix_of_stores_is_a_root(s3, monkeypatch):
    endpoint, opts = s3
    for k, v in s3_env(endpoint).items():
        monkeypatch.setenv(k, v)
    from farm.dashboard.app import Dashboard

    store = create_store("s3://shaderball/dash/one.zarr", LAYOUT, {}, storage_options=opts)
    write_shard(store, 0, synthetic_payload(LAYOUT, 0))
    dash = Dashboard(["s3://shaderball/dash"], [])
    rows = dash.job_rows()
    assert [r["name"] for r in rows] == ["0/one.zarr"] and rows[0]["error"] is None
    assert rows[0]["label"] == "s3://shaderball/dash/one.zarr"
    assert rows[0]["frames_done"] == 4 and rows[0]["status"] == "no state"
    ctx = dash.job_context("0/one.zarr")
    assert ctx["committed"] == 1 and ctx["thumbs"] == [0, 1, 2, 3]
    assert dash.picture("s3://shaderball/dash/one.zarr", 0, False)[:4] == b"\x89PNG"
