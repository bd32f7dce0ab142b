"""The project's error types: the line between a user's mistake and a bug.

``UserError`` is a problem with what the user gave us -- a flag, a config, a dataset, a
checkpoint, a capture, an output path -- or with the machine under it (a full disk). The
``llrmpp`` command prints its message as one line and exits with the error's
``exit_status``; the message says what, where, expected vs got and, where it helps, what to
do. Every other exception is a bug in this library: the command lets its traceback through.

Exit statuses of ``llrmpp``: 0 done; 1 a bug (traceback); 2 bad input (a flag, a config,
a file); 3 out of space (a full disk or quota, a file-size limit, a read-only file
system); 4 a lost peer in multi-host training; 128 + N stopped by signal N after a
checkpoint (130: interrupted at once).

Both subclass the built-in a caller would catch without knowing this module (``ValueError``;
``FileNotFoundError`` for a missing input), so library code can be used as before.
"""

from __future__ import annotations


class UserError(ValueError):
    """A problem with the user's input or environment: reported as one line, exit 2."""

    exit_status = 2


class MissingInputError(UserError, FileNotFoundError):
    """An input file or folder the user named does not exist."""


class OutOfSpaceError(UserError, OSError):
    """An output could not be written: the disk (or a file-size limit) is full. What was
    written before is intact; the message names the path. Exit status 3, so a scheduler
    can tell "out of disk" from a bad config."""

    exit_status = 3


class PeerLostError(UserError, RuntimeError):
    """Another process of a multi-host run stopped answering (killed, out of memory, a lost
    machine). Exit status 4: start every process again to resume from the last complete
    checkpoint."""

    exit_status = 4
