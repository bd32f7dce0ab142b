"""Multi-host data parallelism on CPU: two processes (``jax.distributed.initialize``,
gloo collectives, 2 CPU devices each = a 4-device mesh) each feed only their own half
of every global batch. After 3 steps the parameters equal a plain single-device
full-batch oracle, and the checkpoint both processes wrote restores in one process.
A process killed mid-run ends the other within the watchdog's bound, in one line naming
it (exit status 4); starting both again resumes to the oracle's parameters.

Run as a module (``python -m tests.train.test_multihost MODE PROCESS_ID PORT DIR`` in the
checkout) this file is one of the two processes.
"""

import os
import re
import signal
import socket
import subprocess
import sys
import time

import jax
import numpy as np
import pytest

import tests.conftest  # noqa: F401  (strict jax config, 2 CPU devices, also when run as a module)
from llrmpp_jax.train.checkpoint import restore_checkpoint, save_checkpoint
from llrmpp_jax.train.optimizer import make_optimizer, make_schedule
from llrmpp_jax.train.peers import jax_heartbeat_timeout, watch_peers
from llrmpp_jax.train.sharding import make_data_mesh, replicate_on_mesh, shard_for_mesh
from llrmpp_jax.train.state import init_train_state
from llrmpp_jax.train.step import make_train_step, sharded_train_step
from tests.helpers.environment import ROOT
from tests.helpers.toy_train import (
    CFG,
    assert_tree_close,
    assert_tree_equal,
    oracle_steps,
    toy_batch,
    toy_loss,
    toy_params,
)

N_PROCESSES, GLOBAL_BATCH, STEPS = 2, 8, 3
PEER_TIMEOUT_S, LONG_STEPS = 4.0, 12  # the watchdog's bound; the run the kill interrupts


def global_batch(step: int) -> dict:
    return toy_batch(np.random.default_rng([11, step]), GLOBAL_BATCH)


def initial_state():
    return init_train_state(toy_params(jax.random.key(3)), make_optimizer(CFG), jax.random.key(4))


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


# ``python -c SUPERVISE HINT LOG COMMAND...``: COMMAND under run_supervised, as
# ``llrmpp train --distributed`` runs every process.
SUPERVISE = (
    "import sys; from llrmpp_jax.train.supervise import run_supervised; "
    "sys.exit(run_supervised(sys.argv[3:], sys.argv[1], sys.argv[2]))"
)


def _start(
    mode: str,
    directory,
    stderr=subprocess.STDOUT,
    supervised: tuple[bool, ...] = (False,) * N_PROCESSES,
) -> list[subprocess.Popen]:
    port = _free_port()
    procs = []
    for i, wrap in enumerate(supervised):
        command = [sys.executable, "-m", __name__, mode, str(i), str(port), str(directory)]
        if wrap:
            hint = "resume from the last complete checkpoint in " + os.path.join(directory, "ckpt")
            command = [sys.executable, "-c", SUPERVISE, hint, os.path.join(directory, f"jax_abort_{i}.log"), *command]
        procs.append(subprocess.Popen(command, stdout=subprocess.PIPE, stderr=stderr, text=True, cwd=ROOT))
    return procs


def _run_to_end(mode: str, directory) -> list[str]:
    """Both processes of ``mode``, to the end; each one's output (both must succeed)."""
    procs = _start(mode, directory)
    try:
        logs = [p.communicate(timeout=240)[0] for p in procs]
    finally:
        for p in procs:
            p.kill()
    for p, log in zip(procs, logs):
        assert p.returncode == 0, log[-3000:]
    return logs


def _kill_after_checkpoint(procs: list[subprocess.Popen], victim: int) -> tuple[int, float, str]:
    """SIGKILL ``procs[victim]`` once the other process has saved step 3; the other's exit
    status, the seconds it took to end after the kill, and its stderr."""
    other = procs[1 - victim]
    try:
        for line in other.stdout:  # pyright: ignore[reportOptionalIterable] -- Popen(..., stdout/stderr=PIPE): the stream is set
            if line.strip() == "saved 3":
                break
        else:
            pytest.fail(f"the process ended early: {other.wait()} {other.stderr.read()[-3000:]}")  # pyright: ignore[reportOptionalMemberAccess] -- Popen(..., stdout/stderr=PIPE): the stream is set
        procs[victim].send_signal(signal.SIGKILL)
        killed = time.monotonic()
        status = other.wait(timeout=PEER_TIMEOUT_S + 60)
        return status, time.monotonic() - killed, other.stderr.read()  # pyright: ignore[reportOptionalMemberAccess] -- Popen(..., stdout/stderr=PIPE): the stream is set
    finally:
        for p in procs:
            p.kill()
            p.wait()


def _assert_both_resume(directory) -> None:
    """Both processes started again resume from a checkpoint after step 3 and end at the
    parameters of an uninterrupted run (the single-device oracle)."""
    for log in _run_to_end("long", directory):
        resumed = re.search(r"^resumed at (\d+)$", log, re.MULTILINE)
        assert resumed and 3 <= int(resumed.group(1)) < LONG_STEPS, log[-3000:]
    state0 = initial_state()
    want, _ = oracle_steps(state0.params, make_optimizer(CFG), [global_batch(s) for s in range(LONG_STEPS)])
    restored = restore_checkpoint(directory / "ckpt", state0)
    assert restored.step == LONG_STEPS  # pyright: ignore[reportOptionalMemberAccess] -- a checkpoint was saved above, so restore finds one
    assert_tree_close(restored.state.params, want, atol=1e-5)  # pyright: ignore[reportOptionalMemberAccess] -- a checkpoint was saved above, so restore finds one


def test_two_processes_equal_one_device(tmp_path):
    _run_to_end("steps", tmp_path)
    state0 = initial_state()
    want, _ = oracle_steps(state0.params, make_optimizer(CFG), [global_batch(s) for s in range(STEPS)])
    restored = restore_checkpoint(tmp_path / "ckpt", state0)
    assert restored.step == STEPS and restored.data_state == {"position": STEPS}  # pyright: ignore[reportOptionalMemberAccess] -- a checkpoint was saved above, so restore finds one
    assert_tree_close(restored.state.params, want, atol=1e-5)  # pyright: ignore[reportOptionalMemberAccess] -- a checkpoint was saved above, so restore finds one
    with np.load(tmp_path / "params_process0.npz") as saved:
        from_process = {k: saved[k] for k in saved.files}
    leaves = jax.tree_util.tree_leaves_with_path(restored.state.params)  # pyright: ignore[reportOptionalMemberAccess] -- a checkpoint was saved above, so restore finds one
    assert_tree_equal({jax.tree_util.keystr(p): x for p, x in leaves}, from_process)


def test_a_killed_peer_ends_the_other_in_one_line_and_both_resume(tmp_path):
    """Process 1 is SIGKILLed after a checkpoint; process 0 (the coordinator) stops within
    the watchdog's bound with one line naming process 1 and exit status 4 -- no traceback,
    no JAX abort. Both started again resume from the last complete checkpoint and end at
    the parameters of an uninterrupted run (the single-device oracle)."""
    procs = _start("long", tmp_path, stderr=subprocess.PIPE)
    status, waited, stderr = _kill_after_checkpoint(procs, victim=1)
    assert status == 4, stderr[-3000:]
    assert waited < PEER_TIMEOUT_S + 10, waited
    assert "Traceback" not in stderr and "Check failure" not in stderr and "F0000" not in stderr, stderr[-3000:]
    errors = [line for line in stderr.splitlines() if "llrmpp: error:" in line]
    assert len(errors) == 1 and errors[0].startswith("llrmpp: error: lost process 1 of 2 ("), stderr[-3000:]
    assert f"pid {procs[1].pid})" in errors[0] and "resume from the last complete checkpoint" in errors[0], errors[0]

    _assert_both_resume(tmp_path)


def test_a_killed_coordinator_ends_the_others_in_one_line_and_both_resume(tmp_path):
    """Process 0 (the coordinator, which hosts JAX's coordination service) is SIGKILLed; JAX
    aborts process 1 from a C++ thread at once. Under ``run_supervised`` process 1 still ends
    in one line naming the lost coordinator, exit status 4, JAX's stack dump kept in a file.
    Both started again resume to the parameters of an uninterrupted run."""
    procs = _start("long", tmp_path, stderr=subprocess.PIPE, supervised=(False, True))
    status, waited, stderr = _kill_after_checkpoint(procs, victim=0)
    assert status == 4, stderr[-3000:]
    assert waited < 10, waited
    assert "Traceback" not in stderr and "Check failure" not in stderr and "F1" not in stderr, stderr[-3000:]
    errors = [line for line in stderr.splitlines() if "llrmpp: error:" in line]
    assert len(errors) == 1 and errors[0].startswith("llrmpp: error: lost the coordinator (process 0)"), stderr
    log = tmp_path / "jax_abort_1.log"
    assert str(log) in errors[0] and "resume from the last complete checkpoint in" in errors[0], errors[0]
    assert b"coordination" in log.read_bytes()

    _assert_both_resume(tmp_path)


def _run_process(mode: str, process_id: int, port: str, directory: str) -> None:
    """One host: its own rows of each global batch, a step over the global mesh. ``steps``:
    STEPS steps, then one checkpoint. ``long``: resume from ``directory/ckpt`` if it holds
    one and run to LONG_STEPS, a checkpoint after every step, under the peer watchdog."""
    jax.distributed.initialize(
        coordinator_address=f"127.0.0.1:{port}",
        num_processes=N_PROCESSES,
        process_id=process_id,
        heartbeat_timeout_seconds=jax_heartbeat_timeout(PEER_TIMEOUT_S),
    )
    assert jax.process_count() == N_PROCESSES and jax.device_count() == 2 * N_PROCESSES
    mesh = make_data_mesh()
    step = sharded_train_step(make_train_step(toy_loss, make_optimizer(CFG), make_schedule(CFG)), mesh)
    state = replicate_on_mesh(initial_state(), mesh)
    rows = GLOBAL_BATCH // N_PROCESSES

    def local(s):
        return shard_for_mesh(
            jax.tree.map(lambda x: x[process_id * rows : (process_id + 1) * rows], global_batch(s)), mesh
        )

    ckpt = os.path.join(directory, "ckpt")
    if mode == "long":
        with watch_peers(
            PEER_TIMEOUT_S, interval_s=0.5, resume_hint=lambda: "resume from the last complete checkpoint in " + ckpt
        ):
            restored = restore_checkpoint(ckpt, state)
            start = 0 if restored is None else restored.step
            if restored is not None:
                state = restored.state
                print(f"resumed at {start}", flush=True)
            for s in range(start, LONG_STEPS):
                state, _ = step(state, local(s))
                save_checkpoint(ckpt, state, data_state={"position": s + 1})
                print(f"saved {s + 1}", flush=True)
                time.sleep(0.2)
        return
    for s in range(STEPS):
        state, _ = step(state, local(s))
    save_checkpoint(ckpt, state, data_state={"position": STEPS})
    if process_id == 0:
        leaves = jax.tree_util.tree_leaves_with_path(state.params)
        np.savez(
            os.path.join(directory, "params_process0.npz"),
            **{jax.tree_util.keystr(p): np.asarray(x.addressable_data(0)) for p, x in leaves},  # pyright: ignore[reportArgumentType] -- arrays by keyword; pyright matches the ** to allow_pickle
        )


if __name__ == "__main__":
    _run_process(sys.argv[1], int(sys.argv[2]), sys.argv[3], sys.argv[4])
