"""Errors about what the user asked for."""


class UserError(Exception):
    """A mistake in what the user asked for (a scene, a file, an option): the command
    line prints it as one line and exits with status 2, without a traceback."""
