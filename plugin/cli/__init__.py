"""The ``hlbvh`` command line: its verbs (``command``: doctor, and the table of render,
compare, sweep and bench) and the options they share (``options``)."""

from hlbvh.cli.command import main

__all__ = ["main"]
