"""The one base of the errors a user can fix."""


class UserError(Exception):
    """An error the user can fix: a bad input, a missing file or extra, a store or
    checkpoint that does not fit. Its message is one line that names the culprit; the
    command lines (:class:`shaderball.cli.Commands`) print it and exit 1, with no
    traceback."""
