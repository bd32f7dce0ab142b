"""Multi-host data parallelism on CPU: two processes (``jax.distributed.initialize``,
gloo collectives, 2 CPU devices each = a 4-device mesh) each feed only their own half
of every global batch. After 3 steps the parameters equal a plain single-device
full-batch oracle, and the checkpoint both processes wrote restores in one process.

Run as a script (``python tests/test_train_multihost.py PROCESS_ID PORT DIR``) this file
is one of the two processes.
"""

import os
import socket
import subprocess
import sys

import conftest  # noqa: F401  (strict jax config, 2 CPU devices, also when run as a script)
import jax
import numpy as np
from test_train_step import (
    CFG,
    assert_tree_close,
    assert_tree_equal,
    oracle_steps,
    toy_batch,
    toy_loss,
    toy_params,
)

from llrmpp_jax.train.checkpoint import restore_checkpoint, save_checkpoint
from llrmpp_jax.train.optimizer import make_optimizer, make_schedule
from llrmpp_jax.train.sharding import make_data_mesh, replicate_on_mesh, shard_for_mesh
from llrmpp_jax.train.state import init_train_state
from llrmpp_jax.train.step import make_train_step, sharded_train_step

N_PROCESSES, GLOBAL_BATCH, STEPS = 2, 8, 3


def global_batch(step: int) -> dict:
    return toy_batch(np.random.default_rng([11, step]), GLOBAL_BATCH)


def initial_state():
    return init_train_state(toy_params(jax.random.key(3)), make_optimizer(CFG), jax.random.key(4))


def test_two_processes_equal_one_device(tmp_path):
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    procs = [
        subprocess.Popen(
            [sys.executable, __file__, str(i), str(port), str(tmp_path)],
            stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
        )
        for i in range(N_PROCESSES)
    ]
    try:
        logs = [p.communicate(timeout=240)[0] for p in procs]
    finally:
        for p in procs:
            p.kill()
    for p, log in zip(procs, logs):
        assert p.returncode == 0, log[-3000:]

    state0 = initial_state()
    want, _ = oracle_steps(state0.params, make_optimizer(CFG),
                           [global_batch(s) for s in range(STEPS)])
    restored = restore_checkpoint(tmp_path / "ckpt", state0)
    assert restored.step == STEPS and restored.data_state == {"position": STEPS}
    assert_tree_close(restored.state.params, want, atol=1e-5)
    with np.load(tmp_path / "params_process0.npz") as saved:
        from_process = {k: saved[k] for k in saved.files}
    leaves = jax.tree_util.tree_leaves_with_path(restored.state.params)
    assert_tree_equal({jax.tree_util.keystr(p): x for p, x in leaves}, from_process)


def _run_process(process_id: int, port: str, directory: str) -> None:
    """One host: its own rows of each global batch, a step over the global mesh."""
    jax.distributed.initialize(coordinator_address=f"127.0.0.1:{port}",
                               num_processes=N_PROCESSES, process_id=process_id)
    assert jax.process_count() == N_PROCESSES and jax.device_count() == 2 * N_PROCESSES
    mesh = make_data_mesh()
    step = sharded_train_step(make_train_step(toy_loss, make_optimizer(CFG), make_schedule(CFG)),
                              mesh)
    state = replicate_on_mesh(initial_state(), mesh)
    rows = GLOBAL_BATCH // N_PROCESSES
    for s in range(STEPS):
        local = jax.tree.map(lambda x: x[process_id * rows:(process_id + 1) * rows],
                             global_batch(s))
        state, _ = step(state, shard_for_mesh(local, mesh))
    save_checkpoint(os.path.join(directory, "ckpt"), state, data_state={"position": STEPS})
    if process_id == 0:
        leaves = jax.tree_util.tree_leaves_with_path(state.params)
        np.savez(os.path.join(directory, "params_process0.npz"),
                 **{jax.tree_util.keystr(p): np.asarray(x.addressable_data(0)) for p, x in leaves})


if __name__ == "__main__":
    _run_process(int(sys.argv[1]), sys.argv[2], sys.argv[3])
