"""Ctrl-C in the ``llrmpp`` process (:mod:`llrmpp_jax.process_exit`): one line, status 130,
whenever it lands. Each case runs a small Python program in a child process and interrupts it."""

from __future__ import annotations

import signal
import subprocess
import sys
import textwrap
import time

PRELUDE = """
import atexit, gc, os, signal, sys, time
from llrmpp_jax import process_exit
atexit.register(lambda: print("teardown ran", file=sys.stderr, flush=True))
process_exit.install()
"""


def _default_ctrl_c() -> None:
    """In the child before ``exec``: xdist workers ignore SIGINT and a child inherits that."""
    signal.signal(signal.SIGINT, signal.SIG_DFL)


def _start(program: str) -> subprocess.Popen:
    """``program`` in a child process, once it has printed "ready" (inside its ``try``)."""
    proc = subprocess.Popen(
        [sys.executable, "-c", program],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        preexec_fn=_default_ctrl_c,
    )
    assert proc.stdout.readline() == "ready\n", proc.stderr.read()  # pyright: ignore[reportOptionalMemberAccess] -- Popen(..., stdout/stderr=PIPE): the stream is set
    return proc


def _interrupt(body: str, grace_s: float = 10.0) -> tuple[int, str, float]:
    """Start PRELUDE + ``body`` (``GRACE_S`` set to ``grace_s``), send one SIGINT once it
    prints "ready": (exit status, stderr, seconds from the signal to the exit)."""
    proc = _start(
        PRELUDE.replace("process_exit.install()", f"process_exit.GRACE_S = {grace_s}\nprocess_exit.install()")
        + textwrap.dedent(body)
    )
    start = time.monotonic()
    proc.send_signal(signal.SIGINT)
    status = proc.wait(timeout=60)
    return status, proc.stderr.read(), time.monotonic() - start  # pyright: ignore[reportOptionalMemberAccess] -- Popen(..., stdout/stderr=PIPE): the stream is set


def test_an_interrupt_python_would_ignore_leaves_at_once():
    """Ctrl-C inside a ``gc`` callback (where jax's start-up was seen to swallow it): Python
    would print 'Exception ignored' and carry on; the process leaves, one line, no teardown."""
    program = PRELUDE + textwrap.dedent("""
        def callback(phase, info):
            if phase == "start":
                os.kill(os.getpid(), signal.SIGINT)
                time.sleep(1)  # the handler runs in here
        gc.callbacks.append(callback)
        gc.collect()
        time.sleep(60)
        """)
    start = time.monotonic()
    done = subprocess.run(
        [sys.executable, "-c", program], capture_output=True, text=True, timeout=60, preexec_fn=_default_ctrl_c
    )
    assert (done.returncode, done.stderr) == (130, "llrmpp: interrupted\n")
    assert time.monotonic() - start < 8  # not the 10 s grace


def test_a_command_that_swallows_the_interrupt_leaves_after_the_grace():
    status, err, took = _interrupt(
        """
        try:
            print("ready", flush=True)
            time.sleep(60)
        except KeyboardInterrupt:
            time.sleep(60)  # a finally block that hangs
        """,
        grace_s=1.0,
    )
    assert (status, err) == (130, "llrmpp: interrupted\n")
    assert 1.0 <= took < 30


def test_leave_after_an_interrupt_skips_the_teardown_and_otherwise_runs_it():
    status, err, _ = _interrupt("""
        try:
            print("ready", flush=True)
            time.sleep(60)
        except KeyboardInterrupt:
            process_exit.leave(130)
        """)
    assert (status, err) == (130, "")
    for status in (2, 130):  # 130 without an interrupt: a run that stopped itself on SIGINT, and checkpointed
        done = subprocess.run(
            [sys.executable, "-c", PRELUDE + f"process_exit.leave({status})"], capture_output=True, text=True
        )
        assert (done.returncode, done.stderr) == (status, "teardown ran\n")


def test_a_second_interrupt_leaves_at_once():
    program = PRELUDE + textwrap.dedent("""
        try:
            print("ready", flush=True)
            time.sleep(60)
        except KeyboardInterrupt:
            print("cleaning up", flush=True)
            time.sleep(60)
        """)
    proc = _start(program)
    proc.send_signal(signal.SIGINT)
    assert proc.stdout.readline() == "cleaning up\n"  # pyright: ignore[reportOptionalMemberAccess] -- Popen(..., stdout/stderr=PIPE): the stream is set
    proc.send_signal(signal.SIGINT)
    assert proc.wait(timeout=5) == 130
    assert proc.stderr.read() == "llrmpp: interrupted\n"  # pyright: ignore[reportOptionalMemberAccess] -- Popen(..., stdout/stderr=PIPE): the stream is set


def test_an_ignored_sigint_stays_ignored():
    """``nohup`` and background jobs start a command with SIGINT ignored: it stays so."""
    program = (
        "import signal\nfrom llrmpp_jax import process_exit\nprocess_exit.install()\n"
        "print(signal.getsignal(signal.SIGINT) is signal.SIG_IGN)"
    )
    done = subprocess.run(
        [sys.executable, "-c", program],
        capture_output=True,
        text=True,
        preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_IGN),
    )
    assert done.stdout == "True\n", done.stderr
