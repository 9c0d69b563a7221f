"""Reading a job's materials before it starts: which ones, how many processes, which error."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
from PIL import Image

from farm import validate
from farm.plan import JobConfig, layout_for
from render_jobs.errors import MaterialError
from render_jobs.materials import specs_from_sources
from storage.writer import create_store, write_shard
from tests.storage_helpers import synthetic_payload


def test_usable_cpus_follow_a_cgroup_quota(tmp_path):
    cpu_max = tmp_path / "cpu.max"
    mine = validate.usable_cpus(tmp_path / "none")  # no cgroup file: the affinity
    assert mine >= 1
    cpu_max.write_text("150000 100000\n")  # 1.5 CPUs
    assert validate.usable_cpus(cpu_max) == 1
    cpu_max.write_text("max 100000\n")
    assert validate.usable_cpus(cpu_max) == mine
    cpu_max.write_text("garbage")
    assert validate.usable_cpus(cpu_max) == mine


def test_processes_are_bounded_by_materials_cpus_and_the_cap(monkeypatch):
    monkeypatch.setattr(validate, "usable_cpus", lambda: 16)
    assert [validate.processes(n) for n in (0, 1, 3, 100)] == [1, 1, 3, validate.MAX_PROCESSES]
    monkeypatch.setattr(validate, "usable_cpus", lambda: 2)
    assert validate.processes(100) == 2


def omp_threads(_) -> str | None:
    import os

    return os.environ.get("OMP_NUM_THREADS")


def test_the_reading_processes_share_the_cpus(monkeypatch):
    """Each of the pool's processes reads on its share of the CPUs, or on fewer threads
    where ``OMP_NUM_THREADS`` says so already."""
    monkeypatch.delenv("OMP_NUM_THREADS", raising=False)
    monkeypatch.setattr(validate, "usable_cpus", lambda: 9)  # 4 processes, 2 threads each
    assert list(validate.InOrder(omp_threads, range(5))) == ["2"] * 5
    monkeypatch.setenv("OMP_NUM_THREADS", "1")
    assert list(validate.InOrder(omp_threads, range(5))) == ["1"] * 5


def test_a_resumed_job_reads_only_the_materials_of_uncommitted_shards(tmp_path):
    cfg = JobConfig(sources=("uniform:5",), out=str(tmp_path / "set.zarr"), suns=2,
                    shard_size=4, resolution=32, samples=2)  # fmt: skip
    layout = layout_for(cfg, 5)  # shards of materials [0, 1], [2, 3], [4]
    assert list(validate.pending(cfg, layout)) == [0, 1, 2, 3, 4]  # no store yet
    store = create_store(cfg.out, layout, cfg.dataset_settings())
    write_shard(store, 1, synthetic_payload(layout, 1))
    assert validate.pending(cfg, layout) == [0, 1, 4]
    other = replace(cfg, samples=8)  # another job's store: the submit will refuse it
    assert list(validate.pending(other, layout)) == [0, 1, 2, 3, 4]


def panel(path, grey_roughness=True):
    rng = np.random.default_rng(0)
    arr = rng.integers(0, 256, (16, 80, 3), dtype=np.uint8)
    if grey_roughness:
        arr[:, 48:64] = arr[:, 48:64, :1]
    Image.fromarray(arr).save(path)
    return path


def test_the_error_is_the_first_bad_material_in_job_order(tmp_path, monkeypatch):
    """Read by a pool of processes, the first bad material's error comes back, not the one
    whose read ends first; a job of good ones reads through."""
    monkeypatch.setattr(validate, "usable_cpus", lambda: 2)
    files = [panel(tmp_path / "a.png"), tmp_path / "b.png", panel(tmp_path / "c.png"),
             panel(tmp_path / "d.png", grey_roughness=False)]  # fmt: skip
    files[1].write_bytes(b"not an image")
    specs = specs_from_sources([f"svbrdf:{f}" for f in files], 0)
    with pytest.raises(MaterialError, match="b.png: not a readable image"):
        validate.read_all(specs, progress=False)
    with pytest.raises(MaterialError, match="d.png: roughness panel map is not greyscale"):
        validate.read_all([specs[0], specs[2], specs[3]], progress=False)
    validate.read_all([specs[0], specs[2]], progress=False)


def test_a_job_of_generated_materials_opens_no_store(tmp_path, monkeypatch):
    """Only file materials are read before a job starts; without any, the driver does not
    look at the store (an object store that is down fails once, at the lease)."""
    from farm import driver

    monkeypatch.setattr(driver, "pending", lambda *a: pytest.fail("the store was opened"))
    cfg = JobConfig(sources=("uniform:2", "procedural:1"), out=str(tmp_path / "set.zarr"))
    assert [s.kind for s in driver.validate(cfg, progress=False)] == ["uniform"] * 2 + [
        "procedural"
    ]
