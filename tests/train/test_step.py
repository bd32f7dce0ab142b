"""The data-parallel train step on a toy MLP regression, against a plain single-device
update (value_and_grad of the global-batch loss + optax update, ``tests/helpers/toy_train.py``)."""

import jax
import jax.numpy as jnp
import numpy as np
import optax
import pytest

from llrmpp_jax.train.optimizer import make_optimizer, make_schedule
from llrmpp_jax.train.runner import make_runner
from llrmpp_jax.train.sharding import host_copy, make_data_mesh, replicate_on_mesh, shard_for_mesh
from llrmpp_jax.train.state import init_train_state
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


def _stacked(tree, n: int):
    """pmap's state layout: ``n`` copies of every leaf, ``[...]`` -> ``[n, ...]`` (host arrays)."""
    return jax.tree.map(lambda x: np.broadcast_to(np.asarray(x)[None], (n, *np.shape(x))), tree)


def _split(batch, n: int):
    """pmap's batch layout: ``[B, ...]`` -> ``[n, B/n, ...]``, row ``i`` for device ``i``."""
    return jax.tree.map(lambda x: np.reshape(x, (n, -1, *np.shape(x)[1:])), batch)


def test_two_devices_equal_one_device(key, rng):
    """3 steps of the runner (jit+shard_map over 2 and 1 devices, with and without donating
    the state buffers) == plain oracle."""
    assert jax.local_device_count() == 2
    tx, schedule = make_optimizer(CFG), make_schedule(CFG)
    k_init, k_run = jax.random.split(key)
    state0 = init_train_state(toy_params(k_init), tx, k_run)
    batches = [toy_batch(rng) for _ in range(3)]
    want, history = oracle_steps(state0.params, tx, batches)
    step = make_train_step(toy_loss, tx, schedule)

    for devices, donate in ((jax.devices(), False), (jax.devices()[:1], True)):
        mesh = make_data_mesh(devices)
        sstep = sharded_train_step(step, mesh, donate=donate)
        sstate = replicate_on_mesh(state0, mesh)
        for b in batches:
            sstate, smetrics = sstep(sstate, shard_for_mesh(b, mesh))
        assert_tree_close(sstate.params, want, atol=1e-5)
        assert int(sstate.step) == 3 and int(sstate.skipped) == 0
        # Metrics are global-batch means.
        loss, aux = history[-1]
        assert float(smetrics["loss"]) == pytest.approx(float(loss), rel=1e-5)
        assert float(smetrics["mae"]) == pytest.approx(float(aux["mae"]), rel=1e-5)
        assert float(smetrics["lr"]) == pytest.approx(float(schedule(2)), rel=1e-6)  # pyright: ignore[reportArgumentType] -- float()/int() of a scalar array


def test_the_step_under_pmap_gets_the_runners_result(key, rng):
    """The per-device step stays pmap-ready: under ``jax.pmap`` over 2 devices (the
    compatibility wrapper ``pmap_train_step``) 3 steps give the runner's state and metrics
    (<= 1e-6; both average the same per-device gradients with ``pmean``), the runner's
    matching the plain oracle (test above). A random loss checks that device ``i`` draws
    the same key under both."""
    tx, schedule = make_optimizer(CFG), make_schedule(CFG)
    state0 = init_train_state(toy_params(key), tx, jax.random.fold_in(key, 1))
    batches = [toy_batch(rng) for _ in range(3)]

    def noisy_loss(params, batch, k):
        loss, aux = toy_loss(params, batch, k)
        return loss + 0.1 * jax.random.uniform(k, (), jnp.float32), aux

    step = make_train_step(noisy_loss, tx, schedule)
    runner = make_runner(step, make_data_mesh(), donate=True)
    pstep = pmap_train_step(step)
    state, pstate = runner.place_state(state0), _stacked(state0, 2)
    for b in batches:
        state, metrics = runner.step(state, runner.place_batch(b))
        pstate, pmetrics = pstep(pstate, _split(b, 2))
    got = host_copy(pstate)
    assert_tree_close(jax.tree.map(lambda x: x[1], got), jax.tree.map(lambda x: x[0], got), atol=0)
    assert_tree_close(jax.tree.map(lambda x: x[0], got), host_copy(state), atol=1e-6)
    for k in ("loss", "mae", "grad_norm", "lr", "skipped"):
        assert float(np.asarray(pmetrics[k])[0]) == pytest.approx(float(metrics[k]), rel=1e-6, abs=1e-7), k


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
    norm = lambda b: float(  # noqa: E731
        jax.jit(lambda p: optax.tree.norm(jax.grad(lambda q: toy_loss(q, b, None)[0])(p)))(state0.params)
    )
    threshold = 5 * CFG.grad_clip_norm  # pyright: ignore[reportOperatorIssue] -- CFG sets grad_clip_norm
    assert norm(huge) > threshold > norm(good)
    runner = make_runner(make_train_step(toy_loss, tx, schedule, skip_grad_norm_above=threshold), donate=False)
    state1, m = runner.step(runner.place_state(state0), runner.place_batch(huge))
    assert float(m["grad_norm"]) == pytest.approx(norm(huge), rel=1e-5)
    assert (int(state1.step), int(state1.skipped)) == (1, 1)
    assert [float(m[k]) for k in ("skipped", "skipped_total", "skipped_grad_norm", "skipped_grad_norm_total")] == [
        1.0,
        1.0,
        1.0,
        1.0,
    ]
    assert_tree_equal(state1.params, state0.params)
    adam0, adam1 = state0.opt_state[1][0], state1.opt_state[1][0]  # pyright: ignore[reportIndexIssue] -- an optax state is typed as any pytree; this one is the (named) tuple its transformation builds
    assert_tree_equal((adam1.mu, adam1.nu, adam1.count), (adam0.mu, adam0.nu, adam0.count))  # pyright: ignore[reportAttributeAccessIssue] -- an optax state is typed as any pytree; this one is the (named) tuple its transformation builds
    assert int(state1.opt_state[1][-1].count) == 1  # the schedule's count  # pyright: ignore[reportAttributeAccessIssue, reportIndexIssue] -- an optax state is typed as any pytree; this one is the (named) tuple its transformation builds

    state2, m = runner.step(state1, runner.place_batch(good))
    assert float(m["lr"]) == pytest.approx(float(schedule(1)), rel=1e-6) and float(schedule(1)) > 0  # pyright: ignore[reportArgumentType] -- float()/int() of a scalar array
    assert [float(m[k]) for k in ("skipped", "skipped_total", "skipped_grad_norm_total")] == [0.0, 1.0, 1.0]
    grads = jax.grad(lambda p: toy_loss(p, good, None)[0])(state0.params)
    want = numpy_adamw_first_update(state0.params, grads, float(schedule(1)), CFG)  # pyright: ignore[reportArgumentType] -- float()/int() of a scalar array
    assert_tree_close(state2.params, want, atol=1e-6)


def test_step_key_per_device(key, rng):
    """The loss sees fold_in(fold_in(base, step), device): checked through a metric."""
    tx = make_optimizer(CFG)
    base = jax.random.fold_in(key, 7)
    state0 = init_train_state(toy_params(key), tx, base)

    def noisy_loss(params, batch, k):
        loss, _ = toy_loss(params, batch, k)
        return loss, {"u": jax.random.uniform(k, (), jnp.float32)}

    runner = make_runner(make_train_step(noisy_loss, tx, make_schedule(CFG)))
    state = runner.place_state(state0)
    for s in range(2):
        state, m = runner.step(state, runner.place_batch(toy_batch(rng)))
        want = np.mean(
            [
                float(jax.random.uniform(jax.random.fold_in(jax.random.fold_in(base, s), d), (), jnp.float32))
                for d in (0, 1)
            ]
        )
        assert float(m["u"]) == pytest.approx(want, rel=1e-6)


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
    state1, m = sharded_train_step(step, mesh)(replicate_on_mesh(state0, mesh), shard_for_mesh(batch, mesh))
    assert seen and all(s == {jnp.dtype(jnp.bfloat16)} for s in seen)
    assert {x.dtype for x in jax.tree.leaves((state1.params, state1.opt_state))} <= {
        jnp.dtype(jnp.float32),
        jnp.dtype(jnp.int32),
    }

    def bf16_loss(p, b, k):
        return toy_loss(jax.tree.map(lambda x: x.astype(jnp.bfloat16), p), b, k)

    assert_tree_close(state1.params, oracle_steps(state0.params, tx, [batch], bf16_loss)[0], atol=1e-5)
    f32_loss = float(toy_loss(state0.params, batch, None)[0])
    assert abs(float(m["loss"]) - f32_loss) < 2e-2 * f32_loss


def test_bad_inputs(key, rng):
    tx = make_optimizer(CFG)
    params = toy_params(key)
    with pytest.raises(ValueError, match=r"params\['dense1'\]\['bias'\] has dtype bfloat16"):
        bad = {**params, "dense1": {**params["dense1"], "bias": params["dense1"]["bias"].astype(jnp.bfloat16)}}
        init_train_state(bad, tx, key)
    with pytest.raises(ValueError, match="typed PRNG key"), unchecked():
        init_train_state(params, tx, jax.random.PRNGKey(0))
    with pytest.raises(ValueError, match="batch size 5 does not divide over 2 devices"):
        shard_for_mesh(toy_batch(rng, 5), make_data_mesh())
    with pytest.raises(ValueError, match="share a leading batch axis"):
        shard_for_mesh({"image": np.zeros((4, 3)), "target": np.zeros((6,))}, make_data_mesh())
    with pytest.raises(ValueError, match="compute_dtype=float16"):
        make_train_step(toy_loss, tx, make_schedule(CFG), compute_dtype=jnp.float16)

    mesh = make_data_mesh()
    state = replicate_on_mesh(init_train_state(params, tx, key), mesh)
    batch = shard_for_mesh(toy_batch(rng), mesh)
    vector_loss = make_train_step(lambda p, b, k: (jnp.zeros((2,), jnp.float32), {}), tx, make_schedule(CFG))
    with pytest.raises(ValueError, match=r"loss of shape \(2,\), expected a scalar"):
        sharded_train_step(vector_loss, mesh)(state, batch)
    reserved = make_train_step(lambda p, b, k: (toy_loss(p, b, k)[0], {"lr": jnp.zeros(())}), tx, make_schedule(CFG))
    with pytest.raises(ValueError, match=r"reserved names \['lr'\]"):
        sharded_train_step(reserved, mesh)(state, batch)
    with pytest.raises(ValueError, match="lack the data axis 'batch'"):
        sharded_train_step(reserved, jax.sharding.Mesh(np.asarray(jax.devices()), ("data",)))


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
    samples = [
        make_sample(
            procedural_scene(s, ProceduralConfig(height=res, width=res, num_frames=6)),
            np.array([0, 4]),
            np.array([2]),
            geom,
        )
        for s in (5, 6)
    ]
    batch = {k: np.stack([s[k] for s in samples]) for k in samples[0]}

    def loss_fn(params, b, key):
        del key
        g = reconstruct(params, cfg, b["input_images"], b["input_c2w"], b["input_intrinsics"])
        out = render(params, cfg, g, b["target_c2w"], b["target_intrinsics"], res, res)
        return rgb_loss(
            out.images["rgb"].reshape(-1, res, res, 3),
            b["target_images"].reshape(-1, res, res, 3),
            None,
            perceptual_weight=0.0,
        )

    params = init_params(key, cfg, 2, res, res)
    grads = jax.jit(jax.grad(lambda p: loss_fn(p, batch, None)[0]))(params)
    want = jax.tree.map(lambda p, g: p - g, params, grads)
    tx = optax.sgd(1.0)
    mesh = make_data_mesh()
    step = sharded_train_step(make_train_step(loss_fn, tx, optax.constant_schedule(1.0)), mesh)
    state, metrics = step(replicate_on_mesh(init_train_state(params, tx, key), mesh), shard_for_mesh(batch, mesh))
    assert float(metrics["skipped"]) == 0.0
    assert_tree_close(state.params, want, atol=1e-5)
