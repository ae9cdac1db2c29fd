"""The detector's error classes and exit codes, and the guard that maps them to one line on stderr.

Bad input (a file that is missing, junk, truncated, lacks a field or holds a non-finite value;
an option out of range; an output that cannot be written) raises an :class:`InputError`
subclass whose message names the file or the option. The guard turns exactly those into one
line and exit code 2. Anything else is a bug and keeps its traceback: an internal ``ValueError``
is not bad input.

A leaf: imports nothing of the project.
"""
from __future__ import annotations

import sys
from collections.abc import Callable

EXIT_OK = 0
EXIT_BAD_INPUT = 2
EXIT_TRAIN_FAILED = 3
EXIT_INTERRUPTED = 130


class InputError(Exception):
    """Bad input from the user; the message names the file or option and what is wrong."""


class ConfigError(InputError):
    """A model or training setting, a config file or a command-line option that is not valid."""


class DataError(InputError):
    """A dataroot, table, split, sensor file or results file that is missing or unusable."""


class CheckpointError(InputError):
    """A checkpoint that is missing, corrupt, or of another config or variant."""


class OutputError(InputError):
    """An output path that cannot be written."""


class TrainError(Exception):
    """Training cannot go on (e.g. a non-finite loss); the message says what was kept."""


def run_guarded(fn: Callable[[], object], prog: str = "clfbev") -> int:
    """Run ``fn()`` and return the process exit code: 0, 2 for an :class:`InputError`, 3 for a
    :class:`TrainError`, 130 on Ctrl-C. Every other exception propagates with its traceback."""
    try:
        fn()
        return EXIT_OK
    except InputError as e:
        print(f"{prog}: error: {e}", file=sys.stderr)
        return EXIT_BAD_INPUT
    except TrainError as e:
        print(f"{prog}: error: {e}", file=sys.stderr)
        return EXIT_TRAIN_FAILED
    except KeyboardInterrupt:
        print(f"{prog}: interrupted; rerunning the command with --resume continues from the last checkpoint", file=sys.stderr)
        return EXIT_INTERRUPTED
