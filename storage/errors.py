"""Domain errors of the shard store (messages are one line and name the culprit)."""

from shaderball.errors import UserError


class StoreError(UserError, ValueError):
    """A store is missing, malformed, of another schema, or asked for what it lacks."""


class ShardCommittedError(StoreError):
    """A write to a shard that is already committed (pass ``overwrite=True`` to replace it)."""


class SettingError(UserError, ValueError):
    """An environment variable holds a value this package cannot use."""
