"""The coordinator's death in one line: each process of a distributed run under a small parent.

When process 0 of a multi-host run dies, it takes JAX's coordination service with it, and
JAX's client in every other process aborts at once from a C++ thread (``client.h``: "the JAX
distributed service detected fatal errors"), with a stack dump and SIGABRT, before any
Python code can run (:mod:`llrmpp_jax.train.peers`; ``jax_enable_recoverability`` and the
client's ``missed_heartbeat_callback`` do not prevent it in jax 0.10). So the one line has to
come from outside the process: :func:`run_supervised` runs the command as a child, passes its
standard output through untouched and relays its standard error as it comes, until a line
from JAX's coordination client appears. From there on it keeps the rest in a log file; if
the child then dies, it prints one line naming the lost coordinator and where to resume, and
exits with :class:`~llrmpp_jax.errors.PeerLostError`'s status (4). If the child ends well
after all, the held lines are printed. Its exit status is returned (a signal N as 128 + N,
the shell's convention).

Signals: the child runs in its own process group, so a Ctrl-C in the terminal (or a
scheduler's signal to the job's group) reaches the parent only, which passes SIGINT and
SIGTERM on exactly once: ``train`` checkpoints on the first and stops at once on a second
(:mod:`llrmpp_jax.train.interrupt`). On Linux the child gets SIGTERM if the parent dies.
"""

from __future__ import annotations

import ctypes
import os
import re
import signal
import subprocess
import sys
from typing import BinaryIO

from llrmpp_jax.errors import PeerLostError

# Where JAX's coordination client reports a lost service (its E and F log lines).
MARKERS = (b"coordination_service_agent.cc", b"JAX distributed service detected fatal errors")
# Set in the child, so that a supervised command does not supervise itself again.
ENV = "LLRMPP_SUPERVISED"
# An absl/glog line starts with its severity and the date: "E1128 14:31:01.528557 ...".
_LOG_LINE_START = re.compile(rb"[EFWI]\d{0,4}$|[EFWI]\d{4}[ \d:.]*$")


def _term_with_parent() -> None:
    """In the child before ``exec``: SIGTERM when the parent dies (Linux ``PR_SET_PDEATHSIG``)."""
    ctypes.CDLL(None).prctl(1, int(signal.SIGTERM))


def supervised() -> bool:
    """True inside a child of :func:`run_supervised`."""
    return os.environ.get(ENV) == "1"


def _relay(src: BinaryIO, dst: BinaryIO) -> bytes | None:
    """Copy ``src`` to ``dst`` as it arrives until a line holds one of :data:`MARKERS`;
    return everything from that line on (``None`` if none came). A partial line that could
    be the start of a log line waits for its end; any other (a progress bar's ``\\r``
    update) is written at once."""
    pending = b""
    while chunk := os.read(src.fileno(), 1 << 16):
        pending += chunk
        end = pending.rfind(b"\n") + 1
        lines, pending = pending[:end].splitlines(keepends=True), pending[end:]
        for i, line in enumerate(lines):
            if any(m in line for m in MARKERS):
                held = b"".join(lines[i:]) + pending
                while chunk := os.read(src.fileno(), 1 << 16):
                    held += chunk
                return held
            dst.write(line)
        if pending and not _LOG_LINE_START.match(pending):
            dst.write(pending)
            pending = b""
        dst.flush()
    dst.write(pending)
    dst.flush()
    return None


def run_supervised(command: list[str], resume_hint: str, log_path: str) -> int:
    """Run ``command`` as a child (module docstring); its exit status, or 4 with one line on
    stderr when it died after JAX reported its coordination service lost. The child's C++
    log from that point goes to ``log_path``. ``resume_hint`` completes "start every
    process again to ..."."""
    child = subprocess.Popen(
        command,
        stderr=subprocess.PIPE,
        env=dict(os.environ, **{ENV: "1"}),
        process_group=0,
        preexec_fn=_term_with_parent if sys.platform == "linux" else None,
    )
    forward = {
        sig: signal.signal(sig, lambda s, _frame: child.send_signal(s)) for sig in (signal.SIGINT, signal.SIGTERM)
    }
    try:
        held = _relay(child.stderr, sys.stderr.buffer)  # pyright: ignore[reportArgumentType] -- Popen(..., stderr=PIPE): the stream is set
        status = child.wait()
    finally:
        for sig, handler in forward.items():
            signal.signal(sig, handler)
    if held is not None and status != 0:
        os.makedirs(os.path.dirname(os.path.abspath(log_path)), exist_ok=True)
        with open(log_path, "wb") as f:
            f.write(held)
        print(
            f"llrmpp: error: lost the coordinator (process 0): JAX's distributed service stopped this process "
            f"(pid {child.pid}); start every process again to {resume_hint} (JAX's log: {log_path})",
            file=sys.stderr,
            flush=True,
        )
        return PeerLostError.exit_status
    if held is not None:
        sys.stderr.buffer.write(held)
        sys.stderr.flush()
    return status if status >= 0 else 128 - status
