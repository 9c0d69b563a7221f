"""What every part of shaderball shares and none owns, importing none of them (``farm``,
``render_jobs``, ``storage``, ``trainer``):

- ``errors``: :class:`~shaderball.errors.UserError`, the base of every error a user can fix;
- ``cli``: the click group of every command line (``farm``, ``shards``, ``trainer``), which
  ends a command on a user error in one line;
- ``signals``: SIGTERM unwinding a command as Ctrl-C does;
- ``progress``: the progress bars, drawn on a terminal and written as lines elsewhere;
- ``web``: the guarded web layer of the servers (``farm dashboard``, ``trainer viewer``).
"""
