"""Checkpoints: resume == uninterrupted run (in process, and after a SIGKILL of a
training subprocess), corrupted/truncated/incomplete steps fall back to the previous
good one, incompatible trees fail in one line, keep-last-N.

Run as a module (``python -m tests.train.test_checkpoint DIR`` in the checkout) this file is
the training process that the kill test starts and kills.
"""

import dataclasses
import json
import math
import os
import signal
import subprocess
import sys
import warnings

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import tests.conftest  # noqa: F401  (strict jax config, 2 CPU devices, also when run as a module)
from llrmpp_jax.train.checkpoint import (
    MANIFEST,
    CorruptCheckpointError,
    IncompatibleCheckpointError,
    restore_checkpoint,
    save_checkpoint,
)
from llrmpp_jax.train.optimizer import make_optimizer, make_schedule
from llrmpp_jax.train.runner import make_runner
from llrmpp_jax.train.sharding import host_copy, make_data_mesh, replicate_on_mesh, shard_for_mesh
from llrmpp_jax.train.state import init_train_state
from llrmpp_jax.train.step import make_train_step, sharded_train_step
from tests.helpers.environment import ROOT
from tests.helpers.toy_train import CFG, assert_tree_equal, toy_batch, toy_loss, toy_params

SEED = 1234
NAN_POSITION = 2  # the data stream's batch 2 holds a NaN image: that step is skipped


def noisy_loss(params, batch, key):
    """Toy loss with key-dependent target noise, so the PRNG state matters on resume."""
    noise = 0.1 * jax.random.normal(key, batch["target"].shape, jnp.float32)
    return toy_loss(params, {**batch, "target": batch["target"] + noise}, key)


def batch_at(position: int) -> dict:
    """The data stream: batch number ``position`` (a resumable iterator in one line)."""
    batch = toy_batch(np.random.default_rng([SEED, position]))
    if position == NAN_POSITION:
        batch["image"][3, 0] = np.nan
    return batch


def fresh_state(seed: int = SEED, width: int = 16):
    tx = make_optimizer(CFG)
    return init_train_state(toy_params(jax.random.key(seed), width), tx, jax.random.key(seed + 1))


def toy_runner():
    return make_runner(make_train_step(noisy_loss, make_optimizer(CFG), make_schedule(CFG)))


def run_steps(state, start: int, stop: int, runner=None):
    """Train a host ``state`` on batches ``start..stop-1`` through the runner; a host copy back."""
    runner = runner or toy_runner()
    done = runner.run(state, map(batch_at, range(start, stop)), steps=stop, start=start)
    return host_copy(done.state)


def test_resume_equals_uninterrupted(tmp_path):
    """jit+mesh run: save after k=3 steps, restore into a differently initialised
    template, run 3 more: bitwise equal to 6 uninterrupted steps (incl. a skipped one)."""
    k = 3
    mesh = make_data_mesh()
    step = sharded_train_step(make_train_step(noisy_loss, make_optimizer(CFG), make_schedule(CFG)), mesh)

    def run(state, start, stop):
        for position in range(start, stop):
            state, _ = step(state, shard_for_mesh(batch_at(position), mesh))
        return state

    full = run(replicate_on_mesh(fresh_state(), mesh), 0, 2 * k)
    assert int(full.skipped) == 1

    half = run(replicate_on_mesh(fresh_state(), mesh), 0, k)
    save_checkpoint(tmp_path, half, data_state={"position": k}, config=CFG)
    del half

    template = replicate_on_mesh(fresh_state(seed=99), mesh)
    restored = restore_checkpoint(tmp_path, template)
    assert restored.step == k and restored.data_state == {"position": k}  # pyright: ignore[reportOptionalMemberAccess] -- a checkpoint was saved above, so restore finds one
    assert restored.config == json.loads(json.dumps(dataclasses.asdict(CFG)))  # pyright: ignore[reportOptionalMemberAccess] -- a checkpoint was saved above, so restore finds one
    resumed = run(restored.state, restored.data_state["position"], 2 * k)  # pyright: ignore[reportOptionalMemberAccess] -- a checkpoint was saved above, so restore finds one
    assert_tree_equal(resumed, full)
    assert int(resumed.step) == 2 * k


def test_resume_after_sigkill(tmp_path):
    """A training subprocess (the runner) saving every step is SIGKILLed (possibly mid-save);
    resuming from whatever survives and training to 2j reproduces an uninterrupted run."""
    proc = subprocess.Popen(
        [sys.executable, "-m", __name__, str(tmp_path)],
        stdout=subprocess.PIPE,
        stderr=subprocess.DEVNULL,
        text=True,
        cwd=ROOT,
    )
    try:
        for line in proc.stdout:  # pyright: ignore[reportOptionalIterable] -- Popen(..., stdout/stderr=PIPE): the stream is set
            if line.strip() == "saved 3":
                break
        else:
            pytest.fail(f"training subprocess exited early with code {proc.wait()}")
        os.kill(proc.pid, signal.SIGKILL)
    finally:
        proc.kill()
        proc.wait()

    with warnings.catch_warnings():
        # The kill may land between orbax's commit and the manifest: that step is
        # rejected with a warning and the one before is used.
        warnings.simplefilter("ignore", UserWarning)
        restored = restore_checkpoint(tmp_path, fresh_state(seed=7))
    j = restored.step  # pyright: ignore[reportOptionalMemberAccess] -- a checkpoint was saved above, so restore finds one
    assert j >= 3 and restored.data_state == {"position": j}  # pyright: ignore[reportOptionalMemberAccess] -- a checkpoint was saved above, so restore finds one
    runner, resumed = toy_runner(), restored.state  # pyright: ignore[reportOptionalMemberAccess] -- a checkpoint was saved above, so restore finds one
    for position in range(j, 2 * j):
        # Saving as it goes replaces a step the kill left without a manifest.
        resumed = run_steps(resumed, position, position + 1, runner)
        save_checkpoint(tmp_path, resumed, data_state={"position": position + 1}, keep=2)
    full = run_steps(fresh_state(), 0, 2 * j, runner)
    assert_tree_equal(resumed, full)
    assert_tree_equal(restore_checkpoint(tmp_path, fresh_state(seed=7)).state, full)  # pyright: ignore[reportOptionalMemberAccess] -- a checkpoint was saved above, so restore finds one


@pytest.fixture(scope="module")
def three_states():
    """States after 1, 2, 3 steps of the runner."""
    state, runner, states = fresh_state(), toy_runner(), []
    for position in range(3):
        state = run_steps(state, position, position + 1, runner)
        states.append(state)
    return states


def _largest_file(step_dir):
    files = [p for p in step_dir.rglob("*") if p.is_file() and p.name != MANIFEST]
    return max(files, key=lambda p: p.stat().st_size)


def _flip_byte(step_dir):
    path = _largest_file(step_dir)
    data = bytearray(path.read_bytes())
    data[len(data) // 2] ^= 0xFF
    path.write_bytes(bytes(data))


def _truncate(step_dir):
    path = _largest_file(step_dir)
    path.write_bytes(path.read_bytes()[: path.stat().st_size // 2])


def _drop_manifest(step_dir):
    (step_dir / MANIFEST).unlink()


@pytest.mark.parametrize(
    "damage,message",
    [
        (_flip_byte, "fails its SHA-256 check"),
        (_truncate, "truncated"),
        (_drop_manifest, "save did not complete"),
    ],
)
def test_damaged_checkpoint_falls_back(tmp_path, three_states, damage, message):
    for i, state in enumerate(three_states):
        save_checkpoint(tmp_path, state, data_state={"position": i + 1})
    damage(tmp_path / "3")

    with pytest.warns(UserWarning, match=message):
        restored = restore_checkpoint(tmp_path, fresh_state(seed=5))
    assert restored.step == 2 and restored.data_state == {"position": 2}  # pyright: ignore[reportOptionalMemberAccess] -- a checkpoint was saved above, so restore finds one
    assert_tree_equal(restored.state, three_states[1])  # pyright: ignore[reportOptionalMemberAccess] -- a checkpoint was saved above, so restore finds one

    with pytest.raises(CorruptCheckpointError, match=message):
        restore_checkpoint(tmp_path, fresh_state(seed=5), step=3)

    # The resumed run saves step 3 again: the damaged folder is replaced.
    save_checkpoint(tmp_path, three_states[2], data_state={"position": 3})
    assert_tree_equal(restore_checkpoint(tmp_path, fresh_state(seed=5)).state, three_states[2])  # pyright: ignore[reportOptionalMemberAccess] -- a checkpoint was saved above, so restore finds one


def test_no_good_checkpoint(tmp_path, three_states):
    assert restore_checkpoint(tmp_path / "absent", three_states[0]) is None
    save_checkpoint(tmp_path, three_states[0])
    _truncate(tmp_path / "1")
    with pytest.warns(UserWarning), pytest.raises(CorruptCheckpointError, match="no valid checkpoint"):
        restore_checkpoint(tmp_path, three_states[0])


def test_incompatible_checkpoint(tmp_path, three_states):
    save_checkpoint(tmp_path, three_states[0])
    with pytest.raises(IncompatibleCheckpointError) as err:
        restore_checkpoint(tmp_path, fresh_state(width=8))
    msg = str(err.value)
    assert "\n" not in msg
    assert "does not fit this model" in msg
    assert ".params['dense1']['bias'] is (16,) float32 in the checkpoint, (8,) float32 in the model" in msg


def test_keep_last_n_and_abstract_template(tmp_path, three_states):
    state = three_states[0]
    for s in range(1, 6):
        save_checkpoint(tmp_path, state.replace(step=jnp.asarray(s, jnp.int32)), keep=2)
    assert sorted(int(p.name) for p in tmp_path.iterdir() if p.name.isdigit()) == [4, 5]
    restored = restore_checkpoint(tmp_path, jax.eval_shape(lambda: state))
    assert restored.step == 5  # pyright: ignore[reportOptionalMemberAccess] -- a checkpoint was saved above, so restore finds one
    assert_tree_equal(restored.state.params, state.params)  # pyright: ignore[reportOptionalMemberAccess] -- a checkpoint was saved above, so restore finds one


def test_save_rejects_stacked_per_device_copies(tmp_path, three_states):
    stacked = jax.tree.map(lambda x: np.stack([x, x]), three_states[0])  # pmap's layout of a state
    with pytest.raises(ValueError, match=r"state.step has shape \(2,\), expected \(\)"):
        save_checkpoint(tmp_path, stacked)


@pytest.mark.parametrize("before, after", [("stage", "long_lrm"), ("long_lrm", "stage")])
def test_a_stage_resumes_across_a_change_of_lr_schedule(tmp_path, before, after):
    """A stage checkpointed after 3 steps under one ``StageConfig.lr_schedule`` restores
    under the other: the optimizer state has the same tree (a schedule is a function of
    the update count, not held in the state), the count carries over, and the next 3 steps
    run at the new schedule's rates -- HF's get_cosine_schedule_with_warmup written out
    here (rtol 1e-6) -- bitwise as the same steps run on the unsaved state."""
    from llrmpp_jax.experiment import StageConfig
    from llrmpp_jax.trainer import optimizer_config

    steps, warmup, lr = 8, 2, 1e-2
    mesh = make_data_mesh()

    def optimizer(schedule):
        stage = StageConfig(
            "s",
            steps=steps,
            global_batch=8,
            num_inputs=1,
            num_targets=1,
            resize_h=None,
            lr=lr,
            warmup_steps=warmup,
            lr_schedule=schedule,
        )
        return optimizer_config(stage)

    def hf_rate(schedule, count):
        total = 1_000_000 if schedule == "long_lrm" else steps
        if count < warmup:
            return lr * count / warmup
        return lr * 0.5 * (1.0 + math.cos(math.pi * (count - warmup) / (total - warmup)))

    def run(schedule, state, start, stop):
        cfg = optimizer(schedule)
        step = sharded_train_step(make_train_step(noisy_loss, make_optimizer(cfg), make_schedule(cfg)), mesh)
        rates = []
        for position in range(start, stop):
            state, metrics = step(state, shard_for_mesh(toy_batch(np.random.default_rng([SEED, 9, position])), mesh))
            rates.append(float(metrics["lr"]))
        return state, rates

    def init(schedule, seed):
        state = init_train_state(
            toy_params(jax.random.key(seed)), make_optimizer(optimizer(schedule)), jax.random.key(seed + 1)
        )
        return replicate_on_mesh(state, mesh)

    half, rates_before = run(before, init(before, SEED), 0, 3)
    save_checkpoint(tmp_path, half, data_state={"position": 3})
    template = init(after, 99)
    assert jax.tree.structure(template.opt_state) == jax.tree.structure(half.opt_state)
    restored = restore_checkpoint(tmp_path, template)
    resumed, rates_after = run(after, restored.state, 3, 6)  # pyright: ignore[reportOptionalMemberAccess] -- a checkpoint was saved above, so restore finds one
    direct, _ = run(after, half, 3, 6)
    assert_tree_equal(resumed, direct)
    want = [hf_rate(before, c) for c in range(3)] + [hf_rate(after, c) for c in range(3, 6)]
    np.testing.assert_allclose(rates_before + rates_after, want, rtol=1e-6)


def _train_until_killed(directory: str) -> None:
    """The subprocess of :func:`test_resume_after_sigkill`: save after every step."""
    state, runner = fresh_state(), toy_runner()
    for position in range(1000):
        state = run_steps(state, position, position + 1, runner)
        save_checkpoint(directory, state, data_state={"position": position + 1}, keep=2)
        print(f"saved {position + 1}", flush=True)


if __name__ == "__main__":
    _train_until_killed(sys.argv[1])
