"""A dead peer in multi-host training ends the others in one line, within a bounded time.

When one process of a multi-host run dies (killed, out of memory, a lost machine), the
others wait in a collective that never completes. JAX's coordination service notices the
missing heartbeat after ``heartbeat_timeout_seconds`` and aborts the survivors with a fatal
C++ log (a stack dump, exit status 134) that does not say which process was lost.

:func:`watch_peers` puts a bounded, readable end in front of that: while the ``with``
block runs, a thread in each process writes a counter into the coordination service's
key-value store every ``interval_s`` seconds (``llrmpp/peers/<process index>``), and a
second thread, which makes no network calls and so cannot block, checks how long ago each
peer's counter last moved. A peer silent for ``timeout_s`` seconds -- or, for the
coordinator (process 0, which hosts the store), a store that stopped answering -- is
reported as a :class:`PeerLostError` passed to ``on_lost``. The default
(:func:`exit_lost`) prints ``llrmpp: error: ...`` as one line and ends the process at once
with the error's exit status (4): the main thread is blocked inside XLA, so nothing short
of ``os._exit`` can stop it. Whatever the last complete checkpoint holds is kept (an
unfinished step is removed on the next start), so starting every process again resumes
exactly.

The coordinator itself (process 0) is the exception: its death closes the connection every
other process's JAX client polls, and JAX aborts them at once (SIGABRT with a stack dump
whose first line says the leader task died), before any Python code can run. That line comes from outside the process:
:mod:`llrmpp_jax.train.supervise`, under which ``llrmpp train --distributed`` runs.

The watchdog must fire before JAX's own abort: give ``jax.distributed.initialize`` a
heartbeat timeout above ``timeout_s`` (:func:`jax_heartbeat_timeout`). A process leaving
the block normally marks itself finished, so a peer that finishes its last step later is
not taken for dead. Uses the distributed client of ``jax._src.distributed`` (JAX has no
public handle on its key-value store).
"""

from __future__ import annotations

import contextlib
import os
import socket
import sys
import threading
import time
from collections.abc import Callable, Iterator

import jax

from llrmpp_jax.errors import PeerLostError

_KEY = "llrmpp/peers/"
_DONE = "done"


def jax_heartbeat_timeout(timeout_s: float) -> int:
    """The ``heartbeat_timeout_seconds`` to give ``jax.distributed.initialize`` so that
    :func:`watch_peers` with ``timeout_s`` reports a lost peer before JAX aborts."""
    return int(2 * timeout_s + 10)


def exit_lost(error: PeerLostError) -> None:
    """Print ``error`` as one line on stderr and end the process with its exit status."""
    print(f"llrmpp: error: {error}", file=sys.stderr, flush=True)
    os._exit(error.exit_status)


def _client():
    from jax._src import distributed

    client = distributed.global_state.client
    if client is None:
        raise RuntimeError("watch_peers needs jax.distributed.initialize() first")
    return client


@contextlib.contextmanager
def watch_peers(
    timeout_s: float,
    *,
    interval_s: float = 1.0,
    on_lost: Callable[[PeerLostError], None] = exit_lost,
    resume_hint: Callable[[], str] = lambda: "",
) -> Iterator[None]:
    """Watch the other processes of this multi-host run for the ``with`` block (a no-op
    with one process). ``on_lost`` is called once, from a watchdog thread, with a
    :class:`PeerLostError` naming the first silent process (index, host and PID as it
    last reported them) and ending with ``resume_hint()`` (e.g. the last complete
    checkpoint's step)."""
    if timeout_s <= 0 or interval_s <= 0:
        raise ValueError(f"watch_peers: timeout_s and interval_s must be > 0, got {timeout_s}, {interval_s}")
    count, me = jax.process_count(), jax.process_index()
    if count == 1:
        yield
        return
    client = _client()
    identity = f"{socket.gethostname()} pid {os.getpid()}"
    peers = [p for p in range(count) if p != me]
    start = time.monotonic()
    seen = {p: ("", start) for p in peers}  # peer -> (last value, when it last changed)
    store_ok = [start]  # when the key-value store last answered
    stop = threading.Event()
    lock = threading.Lock()

    def beat() -> None:
        n = 0
        while not stop.is_set():
            n += 1
            try:
                client.key_value_set(f"{_KEY}{me}", f"{n} {identity}", allow_overwrite=True)
                values = {p: client.key_value_try_get(f"{_KEY}{p}") for p in peers}
            except Exception:  # noqa: BLE001 -- the store is gone or not yet written: judged by age below
                values = {}
                for p in peers:
                    with contextlib.suppress(Exception):
                        values[p] = client.key_value_try_get(f"{_KEY}{p}")
            now = time.monotonic()
            with lock:
                if values:
                    store_ok[0] = now
                for p, v in values.items():
                    if v != seen[p][0]:
                        seen[p] = (v, now)
            stop.wait(interval_s)

    def judge() -> None:
        while not stop.wait(interval_s / 2):
            now = time.monotonic()
            with lock:
                silent = [
                    (p, now - t, v) for p, (v, t) in seen.items() if not v.startswith(_DONE) and now - t > timeout_s
                ]
                store_silent = now - store_ok[0] > timeout_s
            if store_silent and me != 0:
                silent = [(0, now - store_ok[0], seen.get(0, ("", 0))[0])]
            if silent:
                p, age, last = silent[0]
                who = f"process {p} of {count}" + (
                    f" ({last.split(' ', 1)[1]})" if " " in last else ""
                )  # "n host pid X"
                hint = resume_hint()
                on_lost(
                    PeerLostError(
                        f"lost {who}: no heartbeat for {age:.0f} s, so this process (process {me}) stops"
                        + (f"; {hint}" if hint else "")
                    )
                )
                return

    threads = [threading.Thread(target=f, name=f"llrmpp-peers-{f.__name__}", daemon=True) for f in (beat, judge)]
    for t in threads:
        t.start()
    try:
        yield
    finally:
        stop.set()
        for t in threads:
            t.join(timeout=2 * interval_s + 1)
        with contextlib.suppress(Exception):
            client.key_value_set(f"{_KEY}{me}", f"{_DONE} {identity}", allow_overwrite=True)
