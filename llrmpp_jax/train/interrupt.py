"""Stop a training run cleanly on SIGINT (Ctrl-C) or SIGTERM (``kill``, a job scheduler).

Inside :func:`stop_on_signals` the first such signal only records that a stop was asked
for; the training loop finishes its current step, saves a checkpoint and returns, so the
same command resumes where it stopped (a plain SIGKILL loses the steps since the last
periodic checkpoint). The first signal also puts the previous handlers back: a second
Ctrl-C raises ``KeyboardInterrupt`` at once, as it would without this.
"""

from __future__ import annotations

import contextlib
import signal
import threading
from collections.abc import Iterator


class StopRequest:
    """Set by a signal handler: ``signal_name`` ("SIGINT", "SIGTERM") once a stop is asked for."""

    def __init__(self) -> None:
        self.signal_name: str | None = None

    def __bool__(self) -> bool:
        return self.signal_name is not None


@contextlib.contextmanager
def stop_on_signals(signals: tuple[signal.Signals, ...] = (signal.SIGINT, signal.SIGTERM)) -> Iterator[StopRequest]:
    """Within the block, ``signals`` set the yielded :class:`StopRequest` instead of stopping
    the process; the handlers in place before are restored on exit (and on the first signal).
    Off the main thread (where Python cannot install handlers) the request is never set."""
    request = StopRequest()
    if threading.current_thread() is not threading.main_thread():
        yield request
        return
    previous = {s: signal.getsignal(s) for s in signals}

    def restore() -> None:
        for s, handler in previous.items():
            signal.signal(s, handler)

    def handler(signum: int, frame: object) -> None:
        request.signal_name = signal.Signals(signum).name
        restore()

    for s in signals:
        signal.signal(s, handler)
    try:
        yield request
    finally:
        restore()
