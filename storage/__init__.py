"""The shard store: the dataset, as one zarr v3 group of screen-space maps and renders.

Schema version 1 (``storage.schema``):

- ``maps``      ``(M, 11, H, W) uint8``  per material: diffuse (3) and specular (3) sRGB-encoded,
  roughness (1), normal (3, (n+1)/2), coverage mask (1); premultiplied by coverage like the
  render job's screen maps. uint8 because the source maps are 8-bit textures (the paper's are
  8-bit PNGs), sRGB keeps dark colours as precise as 8-bit maps allow, and it halves bytes
  against float16 and compresses better.
- ``renders``   ``(N, 3, H, W) float16`` per sample: linear HDR radiance (float16 holds it
  to ~1e-3 relative, up to 65504). A store whose settings have ``render_bits`` B keeps only B
  of the 10 mantissa bits (``farm submit --render-bits``): smaller, for a store that must
  travel, and still far more precise than a render's Monte Carlo noise.
- ``material_index (N,) int32``, ``sun_direction (N, 3) float32``, ``turbidity (N,) float32``,
  ``seed (N,) int64``, ``render_seconds (N,) float32``.
- group attributes ``shaderball``: schema version, layout (resolution, suns per material,
  shard size, counts), render settings, camera, geometry hash, software versions.
- ``commits/NNNNNN.json``: one record per committed shard (its materials' kind, source id and
  spec; byte sizes of its shard files), written atomically after the shard's bytes are durable.
- ``screen_uv.npz`` (optional): the ball's UV layout as the camera sees it, per sub-pixel
  sample (``render_jobs.screen_uv``), written once, atomically, by the farm.

Materials come ``suns_per_material`` samples each, consecutively; a shard holds
``shard_size`` samples (a multiple of the suns, so all suns of a material share a shard) and
the maps of those materials. Chunks are one sample (one material) inside zarr's sharding
codec, zstd-compressed, with crc32c on every chunk and on every shard index. A shard is written
whole by one writer and becomes visible only with its commit record. Importing ``storage``
never loads Blender.

Modules: ``schema`` (the format, stated once), ``writer`` (create stores, write and commit
shards), ``reader`` (``Store``: random access and whole shards), ``chunks`` (direct chunk
reads), ``catalog`` (stores as one set, split by material), ``verify`` and ``summary`` (what
``shards verify`` / ``ls`` / ``info`` print), ``convert`` (farm results into shards),
``backend`` (local files or object stores, atomic writes), ``cli`` (``shards``).
"""

from storage.errors import StoreError

__all__ = ["StoreError"]
