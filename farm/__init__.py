"""The render farm: plans materials x suns into render tasks and runs them on Blender workers.

- ``farm.plan``: the seeded, shard-aligned plan (no Ray);
- ``farm.worker``: the Ray actor around one kept-loaded Blender process;
- ``farm.driver``: ``farm submit``: Ray (embedded or a cluster), retries, blocklisting,
  timeouts, recycling, shard commits, resume;
- ``farm.state`` / ``farm.status``: the job state kept with the store, ``farm status``;
- ``farm.cli``: ``farm submit``, ``farm status``, ``farm preview``.

Importing ``farm`` never loads Blender (nor Ray: the driver imports it when a job starts).
"""
