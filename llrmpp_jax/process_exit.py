"""How the ``llrmpp`` process leaves after Ctrl-C: at once, with one line and status 130.

Two things go wrong with Python's default ``KeyboardInterrupt`` in a JAX program, both seen
when Ctrl-C lands while JAX starts its CPU backend (the first second or two of a command):

- the exception is raised inside a callback Python calls from C (jax's ``gc`` callback)
  and is printed as a traceback and *ignored*: the command carries on and, for ``view``,
  serves forever;
- the exception reaches :func:`llrmpp_jax.cli.main`, which prints ``llrmpp: interrupted``
  and returns 130, and the interpreter's teardown then crashes (SIGSEGV) on XLA's threads.

So the first Ctrl-C raises ``KeyboardInterrupt`` as usual (``finally`` blocks run, the
viewer stops its server). An interrupt that Python would ignore (``sys.unraisablehook``)
leaves at once instead, and a timer covers the rest: a process still alive :data:`GRACE_S`
seconds after Ctrl-C leaves without teardown. A second Ctrl-C leaves at once. :func:`leave` skips
the interpreter's teardown after an interrupt. ``train`` is unaffected while it trains: it
installs its own handlers (:mod:`llrmpp_jax.train.interrupt`) to checkpoint first.
"""

from __future__ import annotations

import os
import signal
import sys
import threading
from typing import NoReturn

GRACE_S = 10.0  # seconds an interrupted command has for its ``finally`` blocks
INTERRUPTED = 128 + signal.SIGINT  # the shell's status for a command stopped by Ctrl-C


def _flush() -> None:
    """Write out what was printed: ``os._exit`` does not."""
    for stream in (sys.stdout, sys.stderr):
        try:
            stream.flush()
        except (OSError, ValueError):  # a closed pipe: nothing more can be said
            pass


def _leave_now() -> NoReturn:
    """Flush what was printed, say so on stderr, and end the process without teardown."""
    _flush()
    os.write(2, b"llrmpp: interrupted\n")
    os._exit(INTERRUPTED)


_interrupted = threading.Event()


def _on_interrupt(signum: int, frame: object) -> None:
    if _interrupted.is_set():  # the second Ctrl-C: the user means it
        _leave_now()
    _interrupted.set()
    timer = threading.Timer(GRACE_S, _leave_now)
    timer.daemon = True
    timer.start()
    raise KeyboardInterrupt


def install() -> None:
    """Make Ctrl-C leave as described above. Call once, in the main thread, before JAX loads.
    A SIGINT that the parent set to be ignored (``nohup``, a background job) stays ignored."""
    if signal.getsignal(signal.SIGINT) is signal.SIG_IGN:
        return
    signal.signal(signal.SIGINT, _on_interrupt)
    report_unraisable = sys.unraisablehook

    def unraisable(info: sys.UnraisableHookArgs) -> None:
        if issubclass(info.exc_type, KeyboardInterrupt):  # Ctrl-C landed in a callback from C
            _leave_now()
        report_unraisable(info)

    sys.unraisablehook = unraisable


def leave(status: int) -> NoReturn:
    """End the process with ``status``; after a Ctrl-C that raised ``KeyboardInterrupt``
    without the interpreter's teardown, which can crash while XLA's threads are mid-start
    (see the module docstring). A run that stopped itself on a signal (``train``'s checkpoint
    and 128 + N) has finished its work and leaves normally."""
    if status == INTERRUPTED and _interrupted.is_set():
        _flush()
        os._exit(status)
    sys.exit(status)
