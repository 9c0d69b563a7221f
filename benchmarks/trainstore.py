"""The small 400² store the training and inference benchmarks read, made by the real farm.

``out/bench-400.zarr``: 4 uniform + 4 procedural materials x 5 suns at 400², 4 spp (the
benchmarks time the network and the loader, not the renders' noise). Made once, then reused;
copy it to a GPU machine to benchmark there (``--store``).
"""

from __future__ import annotations

from pathlib import Path

DEFAULT = "out/bench-400.zarr"


def ensure_store(path: str = DEFAULT) -> str:
    """``path`` if it holds a store, else a fresh one rendered there by ``farm submit``."""
    if (Path(path) / "zarr.json").exists():
        return path
    from farm.driver import submit
    from farm.plan import JobConfig

    print(f"rendering the benchmark store {path} (40 frames at 400², 4 spp; once)", flush=True)
    cfg = JobConfig(
        sources=("uniform:4", "procedural:4"), out=path, resolution=400, samples=4, shard_size=10
    )
    summary = submit(cfg, progress=False, echo=lambda *_: None)
    if not summary.ok:
        raise RuntimeError(f"benchmark store failed: {summary.failed_materials}")
    return path
