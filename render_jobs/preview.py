"""Render one material locally (no Ray) and write everything a person needs to look at it.

Output folder (written to a hidden temporary folder beside it, moved in only when every
render succeeded, so a failed preview leaves nothing half written):

- ``maps.exr`` (screen maps, linear, float32) and ``map_<name>.png`` for each map;
- ``sun_<k>.exr`` (linear HDR radiance) and ``sun_<k>.png`` (tonemapped) for each sun;
- ``contact_sheet.png``: maps over renders, labelled with sun elevation, azimuth, turbidity;
- ``preview.json``: material spec, render settings, suns, seeds, timings, geometry hash.
"""

from __future__ import annotations

import json
import shutil
import tempfile
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

from PIL import Image

from render_jobs.contact_sheet import contact_sheet, display_maps
from render_jobs.exr import write_exr, write_image_exr
from render_jobs.materials.maps import MaterialMaps
from render_jobs.materials.sources import load_maps, one_material
from render_jobs.process import RenderProcess
from render_jobs.results import MaterialRender
from render_jobs.specs import MaterialSpec, RenderSettings, derive_seed
from render_jobs.sun import suns_for_material
from render_jobs.tonemap import to_uint8, tonemap


@dataclass
class Preview:
    out: Path
    spec: MaterialSpec
    result: MaterialRender


def prepare(material: str, seed: int = 0) -> tuple[MaterialSpec, MaterialMaps]:
    """Resolve and validate ``material`` (any form of
    :func:`render_jobs.materials.sources.one_material`; raises :class:`MaterialError`;
    renders nothing)."""
    spec = one_material(material, seed)
    return spec, load_maps(spec)


def render_preview(
    spec: MaterialSpec,
    maps: MaterialMaps,
    out: Path,
    settings: RenderSettings,
    suns: int = 5,
    seed: int = 0,
    on_progress: Callable[[int], None] | None = None,
) -> Preview:
    """Render validated ``maps`` under ``suns`` seeded suns into the folder ``out``. The
    temporary folder is made first, so an output folder that cannot be written fails before
    anything renders; ``on_progress`` gets 0 once it is made (Blender loads after it), then
    the number of frames done after each frame."""
    sun_list = suns_for_material(seed, 0, suns)
    seeds = [derive_seed(seed, 0, k) for k in range(suns)]
    out = Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=f".{out.name}.", dir=out.parent))
    try:
        if on_progress:
            on_progress(0)
        with RenderProcess(settings) as worker:
            result = worker.render_material(maps, sun_list, seeds, on_progress=on_progress)
        _write(tmp, spec, settings, result)
        out.mkdir(exist_ok=True)
        for f in sorted(tmp.iterdir()):
            f.replace(out / f.name)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    return Preview(out=out, spec=spec, result=result)


def _write(folder: Path, spec: MaterialSpec, settings: RenderSettings, r: MaterialRender) -> None:
    channels = {}
    for name, arr in r.maps.as_dict().items():
        for i, c in enumerate("RGB"[: arr.shape[0]] if arr.shape[0] > 1 else "Y"):
            channels[f"{name}.{c}"] = arr[i]
    write_exr(folder / "maps.exr", channels)
    for name, img in display_maps(r.maps).items():
        Image.fromarray(img).save(folder / f"map_{name}.png")
    labels = []
    for k, sr in enumerate(r.renders):
        write_image_exr(folder / f"sun_{k}.exr", sr.radiance)
        Image.fromarray(to_uint8(tonemap(sr.radiance))).save(folder / f"sun_{k}.png")
        labels.append((sr.radiance, f"sun {k}: {sr.sun.label()}"))
    title = f"{spec.source_id}  {settings.resolution}px {settings.samples}spp"
    contact_sheet(r.maps, labels, title).save(folder / "contact_sheet.png")
    meta = {
        "material": spec.to_dict(),
        "settings": settings.to_dict(),
        "geometry_hash": r.geometry_hash,
        "renders": [
            {"sun": sr.sun.to_dict(), "seed": sr.seed, "timings": sr.timings} for sr in r.renders
        ],
    }
    (folder / "preview.json").write_text(json.dumps(meta, indent=2) + "\n")
