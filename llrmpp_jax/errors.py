"""The project's error types: the line between a user's mistake and a bug.

``UserError`` is a problem with what the user gave us -- a flag, a config, a dataset, a
checkpoint, a capture, an output path -- or with the machine under it (a full disk). The
``llrmpp`` command prints its message as one line and exits with status 2; the message says
what, where, expected vs got and, where it helps, what to do. Every other exception is a
bug in this library: the command lets its traceback through (exit status 1).

Both subclass the built-in a caller would catch without knowing this module (``ValueError``;
``FileNotFoundError`` for a missing input), so library code can be used as before.
"""

from __future__ import annotations


class UserError(ValueError):
    """A problem with the user's input or environment: reported as one line, exit 2."""


class MissingInputError(UserError, FileNotFoundError):
    """An input file or folder the user named does not exist."""


class OutOfSpaceError(UserError, OSError):
    """An output could not be written: the disk (or a file-size limit) is full. What was
    written before is intact; the message names the path."""
