"""One training run per workdir: an exclusive OS file lock held for the whole run.

``train`` takes ``<workdir>/.llrmpp.lock`` with ``fcntl.flock(LOCK_EX | LOCK_NB)`` and
writes its PID and host into it. The kernel releases the lock when the process ends in
any way (a SIGKILL included), so a dead run never leaves a stale lock: the file may stay,
its lock does not. A second ``train`` on the same workdir fails at once with
:class:`WorkdirBusyError` naming the holder. Readers (``eval``, ``render`` of a workdir
being trained) take no lock: they read the newest complete checkpoint. In a multi-host
run only process 0 takes it (the others share its workdir).

``flock`` locks are per open file description on one machine; on a network file system
without lock support two hosts could both acquire it, which this cannot detect.
"""

from __future__ import annotations

import contextlib
import fcntl
import os
import socket
from collections.abc import Iterator

from llrmpp_jax.errors import UserError

LOCK_NAME = ".llrmpp.lock"


class WorkdirBusyError(UserError):
    """Another process holds the workdir's lock (a user error: one line, exit status 2)."""


@contextlib.contextmanager
def workdir_lock(workdir: str) -> Iterator[str]:
    """Hold ``workdir``'s exclusive lock (creating the folder) for the ``with`` block;
    yields the lock file's path. :class:`WorkdirBusyError` if another process holds it."""
    os.makedirs(workdir, exist_ok=True)
    path = os.path.join(workdir, LOCK_NAME)
    fd = os.open(path, os.O_RDWR | os.O_CREAT, 0o644)
    try:
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            holder = os.pread(fd, 256, 0).decode(errors="replace").strip() or "unknown process"
            raise WorkdirBusyError(
                f"{workdir}: another llrmpp train is using this workdir ({holder}); wait for it to finish or "
                "stop it, or train in another --workdir"
            ) from None
        os.ftruncate(fd, 0)
        os.pwrite(fd, f"pid {os.getpid()} on {socket.gethostname()}\n".encode(), 0)
        yield path
    finally:
        os.close(fd)  # closing the descriptor releases the lock
