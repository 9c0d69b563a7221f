"""Domain errors of the render job. Messages are one line and name the culprit."""

from shaderball.errors import UserError


class MaterialError(UserError, ValueError):
    """A material source is unusable: the message names the file (or source) and the problem."""


class RenderError(UserError, RuntimeError):
    """Blender failed to render, or its worker process died."""


class WorkerDied(RenderError):
    """The Blender worker process exited (crash, kill, or a failed start)."""
