"""Material sources: specs in, validated texture maps out (numpy, PIL; no ``bpy``).

Source strings (the farm's ``--materials``, the preview's ``--material``):

- ``uniform:N``: N random spatially-constant materials (ranges in ``uniform``);
- ``procedural:N``: N procedural SVBRDFs (noise, cells, tiles, scratches; ``procedural``);
- ``svbrdf:DIR`` (or a PATH): every 5-panel PNG in DIR (Deschaintre et al. 2018: photo, normal,
  diffuse, roughness, specular side by side; the photo is ignored) and every sub-folder of
  per-map files, spec-gloss or metal-rough, named as material libraries name them
  (``library``: which file is which map; ``files``: reading and converting them).

``load_maps(spec)`` validates as it loads and raises :class:`MaterialError` with one line that
names the file and the problem; nothing is rendered from a bad material. ``load_map_bytes(spec)``
gives the same maps as the 8-bit textures Blender holds, a file material read without float
maps (what a render worker and the viewer take).
"""

from render_jobs.materials.maps import MapBytes, MaterialMaps
from render_jobs.materials.sources import (
    load_map_bytes,
    load_maps,
    parse_source,
    specs_from_sources,
)

__all__ = [
    "MapBytes",
    "MaterialMaps",
    "load_map_bytes",
    "load_maps",
    "parse_source",
    "specs_from_sources",
]
