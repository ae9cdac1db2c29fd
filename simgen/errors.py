"""The errors a user can fix, and the exit code they end a command with.

Each carries one line that names the file, field or flag and what is allowed. The command line
(:func:`simgen.cli.main`) maps exactly these to :data:`EXIT_BAD_INPUT` with that line on stderr;
any other exception is a bug and keeps its traceback.
"""
from __future__ import annotations

EXIT_BAD_INPUT = 2


class InputError(Exception):
    """Bad input to a command: the message is one line naming what to fix."""


class ConfigError(InputError):
    """Bad settings: a preset's field, a command-line flag, the output folder."""


class DataError(InputError):
    """A file that a command reads back is missing, damaged or unreadable: a scene part, a
    table, an image, a point cloud, lidarseg labels."""


class ClusterError(InputError):
    """``--ray``: Ray is not installed, or the cluster cannot be reached or joined."""
