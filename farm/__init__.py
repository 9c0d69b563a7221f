"""The render farm: plans materials x suns into render tasks and runs them on Blender workers.

- ``farm.plan``: the seeded, shard-aligned plan (no Ray);
- ``farm.actor``: the Ray actor around one kept-loaded Blender process;
- ``farm.scheduler``: the scheduling policy (dispatch, pipelining, retry with backoff,
  blocklist, timeouts), no Ray;
- ``farm.assembly``: results kept until their shard is whole, no Ray;
- ``farm.pool``: joining or starting Ray, the pool of actors;
- ``farm.lease``: one live driver per store;
- ``farm.faults``: fault injection for the tests (off unless its variable is set);
- ``farm.driver``: ``farm submit``'s loop between them: dispatch, wait, commit shards, resume;
- ``farm.state`` / ``farm.status``: the job state kept with the store, ``farm status``;
- ``farm.cli``: ``farm submit``, ``farm status``, ``farm preview``.

Importing ``farm`` never loads Blender (nor Ray: the driver imports it when a job starts).
"""
