"""The data-parallel train step on a toy MLP regression, against a plain single-device
update (value_and_grad of the global-batch loss + optax update, ``tests/helpers/toy_train.py``)."""

import jax
import jax.numpy as jnp
import numpy as np
import optax
import pytest

from llrmpp_jax.train.optimizer import make_optimizer, make_schedule
from llrmpp_jax.train.sharding import (
    make_data_mesh,
    replicate_for_pmap,
    replicate_on_mesh,
    shard_for_mesh,
    shard_for_pmap,
    unreplicate,
)
from llrmpp_jax.train.state import TrainState, init_train_state
from llrmpp_jax.train.step import make_train_step, pmap_train_step, sharded_train_step
from tests.helpers.toy_train import (
    CFG,
    assert_tree_close,
    assert_tree_equal,
    oracle_steps,
    toy_batch,
    toy_loss,
    toy_params,
)
from tests.helpers.typechecks import unchecked


def test_two_devices_equal_one_device(key, rng):
    """3 steps with pmap (2 devices), jit+shard_map (2 and 1 devices) == plain oracle
    (with and without donating the state buffers)."""
    assert jax.local_device_count() == 2
    tx, schedule = make_optimizer(CFG), make_schedule(CFG)
    k_init, k_run = jax.random.split(key)
    state0 = init_train_state(toy_params(k_init), tx, k_run)
    batches = [toy_batch(rng) for _ in range(3)]
    want, history = oracle_steps(state0.params, tx, batches)
    step = make_train_step(toy_loss, tx, schedule)

    pstep = pmap_train_step(step, donate=True)
    pstate = replicate_for_pmap(state0)
    for b in batches:
        pstate, pmetrics = pstep(pstate, shard_for_pmap(b))
    assert_tree_close(unreplicate(pstate).params, want, atol=1e-5)

    for devices, donate in ((jax.devices(), False), (jax.devices()[:1], True)):
        mesh = make_data_mesh(devices)
        sstep = sharded_train_step(step, mesh, donate=donate)
        sstate = replicate_on_mesh(state0, mesh)
        for b in batches:
            sstate, smetrics = sstep(sstate, shard_for_mesh(b, mesh))
        assert_tree_close(sstate.params, want, atol=1e-5)
        assert int(sstate.step) == 3 and int(sstate.skipped) == 0

    # Metrics are global-batch means, the same under both wrappers.
    loss, aux = history[-1]
    for m in (unreplicate(pmetrics), smetrics):
        assert float(m["loss"]) == pytest.approx(float(loss), rel=1e-5)
        assert float(m["mae"]) == pytest.approx(float(aux["mae"]), rel=1e-5)
        assert float(m["lr"]) == pytest.approx(float(schedule(2)), rel=1e-6)


def test_nan_image_step_is_skipped(key, rng):
    """A NaN image: params and opt state bitwise unchanged, counted; the schedule does
    not advance, so the next good step equals one plain update from the start."""
    tx = make_optimizer(CFG)
    state0 = init_train_state(toy_params(key), tx, jax.random.fold_in(key, 1))
    mesh = make_data_mesh()
    sstep = sharded_train_step(make_train_step(toy_loss, tx, make_schedule(CFG)), mesh)
    bad, good = toy_batch(rng), toy_batch(rng)
    bad["image"][5, 1] = np.nan

    state = replicate_on_mesh(state0, mesh)
    state1, m1 = sstep(state, shard_for_mesh(bad, mesh))
    assert_tree_equal(state1.params, state0.params)
    assert_tree_equal(state1.opt_state, state0.opt_state)
    assert (int(state1.step), int(state1.skipped)) == (1, 1)
    assert float(m1["skipped"]) == 1.0 and not np.isfinite(float(m1["loss"]))

    state2, m2 = sstep(state1, shard_for_mesh(good, mesh))
    assert (int(state2.step), int(state2.skipped), float(m2["skipped"])) == (2, 1, 0.0)
    assert_tree_close(state2.params, oracle_steps(state0.params, tx, [good])[0], atol=1e-6)


def numpy_adamw_first_update(params, grads, lr, cfg):
    """One torch-style AdamW step from fresh moments (bias-correction step 1), after
    global-norm clipping at ``cfg.grad_clip_norm``, written out in NumPy float64."""
    g = {k: {n: np.asarray(v, np.float64) for n, v in layer.items()} for k, layer in grads.items()}
    norm = np.sqrt(sum(np.sum(v**2) for layer in g.values() for v in layer.values()))
    clip = min(1.0, cfg.grad_clip_norm / norm)
    out = {}
    for k, layer in params.items():
        out[k] = {}
        for n, p in layer.items():
            p = np.asarray(p, np.float64)
            gc = g[k][n] * clip
            m_hat = (1 - cfg.b1) * gc / (1 - cfg.b1)
            v_hat = (1 - cfg.b2) * gc**2 / (1 - cfg.b2)
            decay = cfg.weight_decay * p if p.ndim >= 2 else 0.0
            out[k][n] = p - lr * (m_hat / (np.sqrt(v_hat) + cfg.eps) + decay)
    return out


def test_large_grad_norm_skip_advances_the_schedule(key, rng):
    """Gradient norm above ``skip_grad_norm_above``: params and Adam moments bitwise
    unchanged, the schedule one step further (Long-LRM's ``scheduler.step()``), counted in
    the metrics. The next good step is therefore a first Adam update (bias correction 1)
    at rate ``schedule(1)`` (> 0, while ``schedule(0)`` = 0 in the warmup): NumPy oracle."""
    tx, schedule = make_optimizer(CFG), make_schedule(CFG)
    state0 = init_train_state(toy_params(key), tx, key)
    huge, good = toy_batch(rng), toy_batch(rng)
    huge["target"] = huge["target"] * 1e4
    norm = lambda b: float(jax.jit(lambda p: optax.tree.norm(jax.grad(lambda q: toy_loss(q, b, None)[0])(p)))(  # noqa: E731
        state0.params))
    threshold = 5 * CFG.grad_clip_norm
    assert norm(huge) > threshold > norm(good)
    step = pmap_train_step(make_train_step(toy_loss, tx, schedule, skip_grad_norm_above=threshold))
    pstate, m = step(replicate_for_pmap(state0), shard_for_pmap(huge))
    state1 = unreplicate(pstate)
    assert float(m["grad_norm"][0]) == pytest.approx(norm(huge), rel=1e-5)
    assert (int(state1.step), int(state1.skipped)) == (1, 1)
    assert [float(m[k][0]) for k in ("skipped", "skipped_total", "skipped_grad_norm", "skipped_grad_norm_total")] \
        == [1.0, 1.0, 1.0, 1.0]
    assert_tree_equal(state1.params, state0.params)
    adam0, adam1 = state0.opt_state[1][0], state1.opt_state[1][0]
    assert_tree_equal((adam1.mu, adam1.nu, adam1.count), (adam0.mu, adam0.nu, adam0.count))
    assert int(state1.opt_state[1][-1].count) == 1  # the schedule's count

    pstate, m = step(pstate, shard_for_pmap(good))
    assert float(m["lr"][0]) == pytest.approx(float(schedule(1)), rel=1e-6) and float(schedule(1)) > 0
    assert [float(m[k][0]) for k in ("skipped", "skipped_total", "skipped_grad_norm_total")] == [0.0, 1.0, 1.0]
    grads = jax.grad(lambda p: toy_loss(p, good, None)[0])(state0.params)
    want = numpy_adamw_first_update(state0.params, grads, float(schedule(1)), CFG)
    assert_tree_close(unreplicate(pstate).params, want, atol=1e-6)


def test_step_key_per_device(key, rng):
    """The loss sees fold_in(fold_in(base, step), device): checked through a metric."""
    tx = make_optimizer(CFG)
    base = jax.random.fold_in(key, 7)
    state0 = init_train_state(toy_params(key), tx, base)

    def noisy_loss(params, batch, k):
        loss, _ = toy_loss(params, batch, k)
        return loss, {"u": jax.random.uniform(k, (), jnp.float32)}

    pstep = pmap_train_step(make_train_step(noisy_loss, tx, make_schedule(CFG)))
    pstate = replicate_for_pmap(state0)
    for s in range(2):
        pstate, m = pstep(pstate, shard_for_pmap(toy_batch(rng)))
        want = np.mean([float(jax.random.uniform(
            jax.random.fold_in(jax.random.fold_in(base, s), d), (), jnp.float32)) for d in (0, 1)])
        assert float(m["u"][0]) == pytest.approx(want, rel=1e-6)


def test_bf16_compute(key, rng):
    """bf16 compute: the loss sees bf16 params, state stays float32, the update equals a
    plain update whose loss casts the params to bf16."""
    tx = make_optimizer(CFG)
    state0 = init_train_state(toy_params(key), tx, key)
    batch = toy_batch(rng)
    seen = []

    def loss(params, b, k):
        seen.append({x.dtype for x in jax.tree.leaves(params)})
        return toy_loss(params, b, k)

    step = make_train_step(loss, tx, make_schedule(CFG), compute_dtype=jnp.bfloat16)
    mesh = make_data_mesh()
    state1, m = sharded_train_step(step, mesh)(replicate_on_mesh(state0, mesh),
                                                shard_for_mesh(batch, mesh))
    assert seen and all(s == {jnp.dtype(jnp.bfloat16)} for s in seen)
    assert {x.dtype for x in jax.tree.leaves((state1.params, state1.opt_state))} <= {
        jnp.dtype(jnp.float32), jnp.dtype(jnp.int32)}

    def bf16_loss(p, b, k):
        return toy_loss(jax.tree.map(lambda x: x.astype(jnp.bfloat16), p), b, k)

    assert_tree_close(state1.params, oracle_steps(state0.params, tx, [batch], bf16_loss)[0], atol=1e-5)
    f32_loss = float(toy_loss(state0.params, batch, None)[0])
    assert abs(float(m["loss"]) - f32_loss) < 2e-2 * f32_loss


def test_bad_inputs(key, rng):
    tx = make_optimizer(CFG)
    params = toy_params(key)
    with pytest.raises(ValueError, match=r"params\['dense1'\]\['bias'\] has dtype bfloat16"):
        bad = {**params, "dense1": {**params["dense1"],
                                    "bias": params["dense1"]["bias"].astype(jnp.bfloat16)}}
        init_train_state(bad, tx, key)
    with pytest.raises(ValueError, match="typed PRNG key"), unchecked():
        init_train_state(params, tx, jax.random.PRNGKey(0))
    with pytest.raises(ValueError, match="batch size 7 does not divide over 2 devices"):
        shard_for_pmap(toy_batch(rng, 7))
    with pytest.raises(ValueError, match="batch size 5 does not divide over 2 devices"):
        shard_for_mesh(toy_batch(rng, 5), make_data_mesh())
    with pytest.raises(ValueError, match="share a leading batch axis"):
        shard_for_pmap({"image": np.zeros((4, 3)), "target": np.zeros((6,))})
    with pytest.raises(ValueError, match="compute_dtype=float16"):
        make_train_step(toy_loss, tx, make_schedule(CFG), compute_dtype=jnp.float16)

    state = replicate_for_pmap(init_train_state(params, tx, key))
    batch = shard_for_pmap(toy_batch(rng))
    vector_loss = make_train_step(lambda p, b, k: (jnp.zeros((2,), jnp.float32), {}), tx,
                                  make_schedule(CFG))
    with pytest.raises(ValueError, match=r"loss of shape \(2,\), expected a scalar"):
        pmap_train_step(vector_loss)(state, batch)
    reserved = make_train_step(lambda p, b, k: (toy_loss(p, b, k)[0], {"lr": jnp.zeros(())}),
                               tx, make_schedule(CFG))
    with pytest.raises(ValueError, match=r"reserved names \['lr'\]"):
        pmap_train_step(reserved)(state, batch)
    assert isinstance(unreplicate(state), TrainState)


@pytest.mark.slow
def test_model_step_sharded_over_two_devices_equals_one_device(key):
    """The real model (tiny: blockwise global attention, chunked SSD scan over 128 tokens
    > chunk 64, k-NN local attention) inside ``shard_map`` over 2 devices: every loop carry
    and custom VJP must keep the batch's device variance. One SGD(lr=1) step equals
    ``params - grad`` of the global-batch loss computed on one device, <= 1e-5."""
    from llrmpp_jax import config as C
    from llrmpp_jax.data import ProceduralConfig
    from llrmpp_jax.data.preprocess import ViewGeometry, make_sample
    from llrmpp_jax.data.synthetic import procedural_scene
    from llrmpp_jax.losses import rgb_loss
    from llrmpp_jax.model import init_params, reconstruct, render

    cfg, res = C.tiny(), 64
    geom = ViewGeometry(resize_h=res, multiple=cfg.size_multiple, square_crop=True)
    samples = [make_sample(procedural_scene(s, ProceduralConfig(height=res, width=res, num_frames=6)),
                           np.array([0, 4]), np.array([2]), geom) for s in (5, 6)]
    batch = {k: np.stack([s[k] for s in samples]) for k in samples[0]}

    def loss_fn(params, b, key):
        del key
        g = reconstruct(params, cfg, b["input_images"], b["input_c2w"], b["input_intrinsics"])
        out = render(params, cfg, g, b["target_c2w"], b["target_intrinsics"], res, res)
        return rgb_loss(out.images["rgb"].reshape(-1, res, res, 3),
                        b["target_images"].reshape(-1, res, res, 3), None, perceptual_weight=0.0)

    params = init_params(key, cfg, 2, res, res)
    grads = jax.jit(jax.grad(lambda p: loss_fn(p, batch, None)[0]))(params)
    want = jax.tree.map(lambda p, g: p - g, params, grads)
    tx = optax.sgd(1.0)
    mesh = make_data_mesh()
    step = sharded_train_step(make_train_step(loss_fn, tx, optax.constant_schedule(1.0)), mesh)
    state, metrics = step(replicate_on_mesh(init_train_state(params, tx, key), mesh), shard_for_mesh(batch, mesh))
    assert float(metrics["skipped"]) == 0.0
    assert_tree_close(state.params, want, atol=1e-5)
