"""The render job in real Blender Cycles (64 px, 8 spp, one kept-loaded worker process)."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import psutil
import pytest

from render_jobs.errors import RenderError
from render_jobs.materials.procedural import procedural_maps
from render_jobs.materials.uniform import uniform_maps
from render_jobs.process import RenderProcess
from render_jobs.sun import sun_from_angles
from tests.conftest import TINY, grey_uniform, inside
from tests.test_farm import wait_until

pytestmark = pytest.mark.slow

RIGHT = sun_from_angles(35, 0, 3.0)  # sun at +X: image right (the camera looks along +Y)
LEFT = sun_from_angles(35, 180, 3.0)


def render(worker, maps, suns, seed=1):
    return worker.render_material(maps, suns, [seed + i for i in range(len(suns))])


def test_render_is_finite_positive_and_lit(worker, grey_maps):
    r = render(worker, grey_maps, [RIGHT])
    x = r.renders[0].radiance
    assert x.shape == (3, TINY.resolution, TINY.resolution) and x.dtype == np.float32
    assert np.all(np.isfinite(x)) and x.min() >= 0.0
    assert x.mean() > 0.02
    assert r.renders[0].seed == 1 and r.renders[0].timings["path_tracing"] > 0


def test_mask_covers_the_ball(worker, grey_maps):
    m = render(worker, grey_maps, [RIGHT]).maps
    assert m.mask.shape == (1, 64, 64)
    assert m.mask[0, 32, 32] > 0.99  # the centre of the frame is the ball
    assert m.mask[0, :3, :].max() == 0 and m.mask[0, -3:, :].max() == 0  # sky, ground
    covered = (m.mask > 0.5).mean()
    assert 0.2 < covered < 0.6
    # maps are zero off the material
    assert np.abs(m.diffuse[:, m.mask[0] == 0]).max() == 0


def test_lit_side_moves_with_the_sun(worker, grey_maps):
    r = render(worker, grey_maps, [RIGHT, LEFT])
    ball = inside(r.maps.mask)
    cols = np.arange(64)[None, :].repeat(64, 0)
    left, right = ball & (cols < 28), ball & (cols > 36)
    lum = [sr.radiance.mean(0) for sr in r.renders]
    assert lum[0][right].mean() > 1.5 * lum[0][left].mean()
    assert lum[1][left].mean() > 1.5 * lum[1][right].mean()


def test_sky_colour_changes_with_turbidity(worker, grey_maps):
    clear, hazy = sun_from_angles(35, 90, 2.0), sun_from_angles(35, 90, 10.0)
    r = render(worker, grey_maps, [clear, hazy])
    sky = [sr.radiance[:, :4, :].reshape(3, -1).mean(1) for sr in r.renders]
    blueness = [s[2] / s[0] for s in sky]
    assert blueness[0] > 1.1 * blueness[1]


def test_red_diffuse_map_makes_a_red_ball_after_another_material(worker):
    render(worker, procedural_maps(7, 64), [RIGHT])  # a textured material first
    red = uniform_maps(grey_uniform(diffuse=(0.9, 0.05, 0.05), specular=(0.02,) * 3), "red")
    r = render(worker, red, [RIGHT])
    ball = inside(r.maps.mask)
    rgb = r.renders[0].radiance[:, ball].mean(1)
    assert rgb[0] > 3 * rgb[1] and rgb[0] > 3 * rgb[2]
    np.testing.assert_allclose(r.maps.diffuse[:, ball].mean(1), [0.787, 0.004, 0.004], atol=0.01)


def test_uniform_maps_are_constant_inside_the_mask(worker):
    values = grey_uniform(
        diffuse=(0.3, 0.5, 0.7),
        specular=(0.2, 0.2, 0.2),
        roughness=0.35,
        normal_tilt_deg=10,
        normal_azimuth_deg=30,
    )
    m = render(worker, uniform_maps(values), [RIGHT]).maps
    ball = inside(m.mask, 0.999)
    for name in ("diffuse", "specular", "roughness", "normal"):
        arr = getattr(m, name)[:, ball]
        assert arr.std(axis=1).max() < 2e-3, name
    assert m.roughness[0, ball].mean() == pytest.approx(0.35, abs=0.005)


def test_same_seed_same_render_other_seed_other_noise(worker, grey_maps):
    a = render(worker, grey_maps, [RIGHT], seed=5).renders[0].radiance
    b = render(worker, grey_maps, [RIGHT], seed=5).renders[0].radiance
    c = render(worker, grey_maps, [RIGHT], seed=6).renders[0].radiance
    np.testing.assert_array_equal(a, b)
    assert not np.array_equal(a, c)
    assert abs(a.mean() - c.mean()) < 0.1 * a.mean()


def test_normal_map_changes_shading(worker):
    flat = render(worker, uniform_maps(grey_uniform()), [RIGHT])
    tilted = render(worker, uniform_maps(grey_uniform(normal_tilt_deg=15)), [RIGHT])
    ball = inside(flat.maps.mask)
    diff = np.abs(flat.renders[0].radiance - tilted.renders[0].radiance)[:, ball].mean()
    assert diff > 0.05 * flat.renders[0].radiance[:, ball].mean()


def test_geometry_is_identical_across_processes(worker):
    with RenderProcess(TINY) as other:
        assert other.info["geometry_hash"] == worker.info["geometry_hash"]
        assert other.pid != worker.pid
    assert len(worker.info["geometry_hash"]) == 64


def test_renders_are_identical_across_processes(worker, grey_maps):
    """Same scene, same seed, another Blender process: the same image, to float rounding
    (Cycles' threads may sum a pixel's samples in another order)."""
    a = render(worker, grey_maps, [RIGHT], seed=9).renders[0].radiance
    with RenderProcess(TINY) as other:
        b = render(other, grey_maps, [RIGHT], seed=9).renders[0].radiance
    np.testing.assert_allclose(a, b, rtol=1e-5, atol=1e-7)


def test_killed_worker_raises_and_restarts(grey_maps):
    w = RenderProcess(TINY).start()
    try:
        render(w, grey_maps, [RIGHT])
        scratch = w.scratch
        assert os.listdir(scratch)  # the texture files live there
        os.kill(w.pid, signal.SIGKILL)
        with pytest.raises(RenderError, match="died"):
            render(w, grey_maps, [RIGHT])
        assert not os.path.exists(scratch)  # the parent cleaned up after the dead child
        again = render(w, grey_maps, [RIGHT])  # a fresh child takes over
        assert np.isfinite(again.renders[0].radiance).all()
        scratch = w.scratch
    finally:
        w.close()
    assert not os.path.exists(scratch)


def test_a_worker_leaves_nothing_in_the_temp_folder(tmp_path, monkeypatch, grey_maps):
    """Blender's session folder (``blender_XXXXXX``, made when bpy loads) goes with the
    scratch folder, whether the child exits or is killed: a farm node starts many."""
    monkeypatch.setenv("TMPDIR", str(tmp_path))
    with RenderProcess(TINY) as w:
        render(w, grey_maps, [RIGHT])
        assert [p.name for p in Path(w.scratch).glob("blender_*")]
        os.kill(w.pid, signal.SIGKILL)
        with pytest.raises(RenderError, match="died"):
            render(w, grey_maps, [RIGHT])
        render(w, grey_maps, [RIGHT])
    assert os.listdir(tmp_path) == []


def test_the_blender_child_runs_nothing_of_its_parents_main_script(tmp_path):
    """The spawned child does not run the calling script again (``_parent_main_hidden``): a
    script without an ``if __name__ == "__main__":`` guard renders, once, and the child of a
    script that imports Ray at its top (as a farm worker's, Ray's ``default_worker.py``,
    does) loads no Ray."""
    script = tmp_path / "no_guard.py"
    script.write_text(
        "import ray\n"
        "from render_jobs.process import RenderProcess\n"
        "from render_jobs.specs import RenderSettings\n"
        "from render_jobs.materials.uniform import uniform_maps\n"
        "from tests.conftest import grey_uniform\n"
        "from render_jobs.sun import sun_from_angles\n"
        "print('script ran', flush=True)\n"
        "with RenderProcess(RenderSettings(resolution=16, samples=1, threads=1)) as w:\n"
        "    print('child has ray:', '_raylet' in open(f'/proc/{w.pid}/maps').read())\n"
        "    sun = sun_from_angles(35, 0, 3)\n"
        "    r = w.render_material(uniform_maps(grey_uniform()), [sun], [0])\n"
        "print('rendered', len(r.renders), flush=True)\n"
    )
    env = {**os.environ, "PYTHONPATH": str(Path(__file__).resolve().parents[1])}
    run = subprocess.run(
        [sys.executable, str(script)], capture_output=True, text=True, timeout=120, env=env
    )
    assert run.returncode == 0, run.stderr[-2000:]
    assert run.stdout.splitlines() == ["script ran", "child has ray: False", "rendered 1"]


# a parent that starts a long render, says so, and waits to be killed; with "thread", from a
# thread other than the main one (where a farm actor's recycled Blender starts)
LONG_RENDER = """
import sys, threading
from render_jobs.materials.procedural import procedural_maps
from render_jobs.process import RenderProcess
from render_jobs.specs import RenderSettings
from render_jobs.sun import sun_from_angles
def render():
    with RenderProcess(RenderSettings(resolution=128, samples=4096, threads=1)) as w:
        print(w.pid, flush=True)
        w.render_material(procedural_maps(0, 64), [sun_from_angles(35, 0, 3.0)], [0])
if __name__ == "__main__":
    if sys.argv[1:] == ["thread"]:
        threading.Thread(target=render).start()
    else:
        render()
"""


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="PR_SET_PDEATHSIG is Linux's")
@pytest.mark.parametrize("where", ["main", "thread"])
def test_a_killed_parent_takes_its_rendering_blender_with_it(tmp_path, where):
    """What a Ray actor killed mid-render does to its Blender child: it ends at once rather
    than rendering on (this render alone takes minutes), whether the main thread or another
    one that lasts started it."""
    script = tmp_path / "parent.py"
    script.write_text(LONG_RENDER)
    env = {**os.environ, "PYTHONPATH": str(Path(__file__).resolve().parents[1])}
    cmd = [sys.executable, str(script), where]
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, env=env)
    child = None
    try:
        child = psutil.Process(int(proc.stdout.readline()))
        wait_until(
            lambda: child.cpu_percent(interval=0.5) >= 50, 60, "the Blender child never rendered"
        )
        proc.kill()
        proc.wait(10)
        child.wait(timeout=10)  # psutil.TimeoutExpired if it renders on
    finally:
        proc.kill()
        if child is not None and child.is_running():
            child.kill()


def cpu_seconds(pid: int) -> float:
    """User + system CPU time of process ``pid``, all its threads."""
    t = psutil.Process(pid).cpu_times()
    return t.user + t.system


@pytest.mark.skipif(
    not hasattr(os, "sched_getaffinity") or len(os.sched_getaffinity(0)) < 2,
    reason="needs Linux and 2 CPUs: the spare thread pool only spins on a spare core",
)
def test_one_thread_worker_keeps_one_core_busy(grey_maps):
    """threads=1 renders use one core, not one plus spinning pool threads (see
    render_jobs.process.thread_pool_of), and the worker may still run on every CPU."""
    with RenderProcess(TINY.__class__(resolution=64, samples=64, threads=1)) as w:
        render(w, grey_maps, [RIGHT])
        c0, t0 = cpu_seconds(w.pid), time.perf_counter()
        render(w, grey_maps, [RIGHT, LEFT, RIGHT])
        busy = (cpu_seconds(w.pid) - c0) / (time.perf_counter() - t0)
        assert os.sched_getaffinity(w.pid) == os.sched_getaffinity(0)
    assert busy < 1.3, f"a 1-thread worker kept {busy:.2f} cores busy"


def test_stale_scratch_of_dead_processes_is_swept(tmp_path):
    from render_jobs.process import SCRATCH_PREFIX, sweep_stale_scratch

    dead = 2**22 + 17  # above the largest pid_max Linux allows: never a live process
    stale = tmp_path / f"{SCRATCH_PREFIX}{dead}-abc"
    live = tmp_path / f"{SCRATCH_PREFIX}{os.getpid()}-abc"
    stale.mkdir()
    live.mkdir()
    sweep_stale_scratch(str(tmp_path))
    assert not stale.exists() and live.exists()


def test_memory_stays_flat_over_50_materials():
    """RSS after 50 materials x 1 sun stays within 60 MB of RSS after the first 10."""
    settings = TINY.__class__(resolution=32, samples=1, threads=2)
    with RenderProcess(settings) as w:
        rss = []
        for i in range(50):
            r = w.render_material(procedural_maps(i, 128), [RIGHT], [i])
            rss.append(r.rss_bytes)
    growth = (rss[-1] - rss[9]) / 2**20
    assert growth < 60, f"RSS grew {growth:.0f} MB over 40 materials"


def test_texture_swaps_never_alias(worker):
    """Material A, then B, then A again: A renders bit-identically, each AOV shows its own map.

    Guards against Cycles' persistent image cache serving a previous material's pixels
    (see render_jobs.blender.shading).
    """
    a = uniform_maps(
        grey_uniform(
            diffuse=(0.8, 0.2, 0.1), specular=(0.3, 0.3, 0.3), roughness=0.2, normal_tilt_deg=12
        ),
        "a",
    )
    b = procedural_maps(3, 64)
    first = render(worker, a, [RIGHT], seed=3)
    render(worker, b, [LEFT], seed=4)
    again = render(worker, a, [RIGHT], seed=3)
    np.testing.assert_array_equal(first.renders[0].radiance, again.renders[0].radiance)
    ball = inside(again.maps.mask)
    np.testing.assert_allclose(again.maps.specular[:, ball].mean(1), 0.073, atol=0.005)
    np.testing.assert_allclose(again.maps.roughness[:, ball].mean(1), 0.2, atol=0.005)
    assert again.maps.normal[0, ball].mean() > 0.55  # tilted towards +x, not flat (0.5)


def test_scratch_goes_to_memory_only_where_it_has_room(tmp_path):
    from render_jobs.process import SCRATCH_ROOM, scratch_parent

    small = tmp_path / "small"  # a tmpfs a little under the room the scratch needs
    small.mkdir()
    r = subprocess.run(
        ["unshare", "-m", "sh", "-c", f"mount -t tmpfs -o size={SCRATCH_ROOM // 2} tmpfs {small}"
         f" && {sys.executable} -c 'from render_jobs.process import scratch_parent as p; "
         f"print(p(\"{small}\"))'"],
        capture_output=True, text=True, cwd=Path(__file__).resolve().parents[1],
    )  # fmt: skip
    if r.returncode != 0 and "unshare" in r.stderr:
        pytest.skip(f"no private mount namespace here: {r.stderr.strip()}")
    assert r.stdout.strip() == "None", r.stderr  # the temp folder instead
    assert scratch_parent(str(tmp_path)) == str(tmp_path)  # a disk with room
    assert scratch_parent(str(tmp_path / "none")) is None
