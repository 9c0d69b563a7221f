"""The render farm: plans materials x suns into render tasks and runs them on Blender workers.

- ``farm.plan``: the seeded, shard-aligned plan (no Ray);
- ``farm.actor``: the Ray actor around one kept-loaded Blender process;
- ``farm.scheduler``: the scheduling policy (dispatch, pipelining, retry with backoff,
  blocklist, timeouts), no Ray;
- ``farm.assembly``: result refs kept until their shard is whole, no Ray;
- ``farm.commit``: a whole shard written as a Ray task next to its data;
- ``farm.cluster``: joining or starting Ray, and the checks of a cluster before a job;
- ``farm.pool``: the pool of actors, the commit tasks;
- ``farm.lease``: one live driver per store;
- ``farm.cancel``: the cancel request a running driver polls;
- ``farm.faults``: fault injection for the tests (off unless its variable is set);
- ``farm.driver``: ``farm submit``'s loop between them: dispatch, wait, commit, resume;
- ``farm.state`` / ``farm.status``: the job state kept with the store, ``farm status``;
- ``farm.materials``: ``farm materials``, the dry run of material sources;
- ``farm.dashboard``: ``farm dashboard``, the web page and ``/metrics``;
- ``farm.cli``: ``farm submit``, ``status``, ``cancel``, ``materials``, ``preview``,
  ``screen-uv``, ``dashboard``.

Its commands and dashboard stand on ``shaderball`` (the click group, SIGTERM unwinding, the
guarded web layer). Importing ``farm`` never loads Blender (nor Ray: the driver imports it
when a job starts).
"""
