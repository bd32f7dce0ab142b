"""The train step's guards as optax wrappers (llrmpp_jax.train.guards), each against its
inner optimizer's own update (the oracle): a kept step is exactly the inner update and
state; a skipped one is a zero update with the inner state kept (non-finite) or only its
schedule one step further (too large). The wrappers hold no state of their own, so an
optimizer state saved without them restores with them."""

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import optax
import pytest

from llrmpp_jax.train.guards import guard_steps, skip_large_gradients, skip_nonfinite, skip_reasons
from llrmpp_jax.train.optimizer import make_optimizer, schedule_count
from tests.helpers.toy_train import CFG, assert_tree_equal, toy_params


def _grads(params, rng, scale=1.0):
    return jax.tree.map(lambda p: jnp.asarray(scale * rng.normal(size=p.shape), jnp.float32), params)


def _update(tx, grads, state, params, **extra):
    with jax.numpy_dtype_promotion("standard"):  # optax's Python-float x int32 count
        return tx.update(grads, state, params, **extra)


def _norm(tree) -> float:
    return float(np.sqrt(sum(np.sum(np.asarray(x, np.float64) ** 2) for x in jax.tree.leaves(tree))))


def _zero(tree) -> bool:
    return all(not np.any(np.asarray(x)) for x in jax.tree.leaves(tree))


@pytest.fixture
def setup(key, rng):
    params = toy_params(key)
    inner = make_optimizer(dataclasses.replace(CFG, warmup_steps=2))
    state = inner.init(params)
    # one applied update first, so the moments and counts are non-zero
    state = _update(inner, _grads(params, rng), state, params)[1]
    return params, inner, state


def test_the_wrappers_keep_the_inner_state_tree(setup):
    params, inner, _ = setup
    for tx in (skip_nonfinite(inner), skip_large_gradients(inner, 5.0), guard_steps(inner, 5.0), guard_steps(inner)):
        a, b = tx.init(params), inner.init(params)
        assert jax.tree.structure(a) == jax.tree.structure(b)
        assert_tree_equal(a, b)


def test_a_kept_step_is_the_inner_update(setup, rng):
    params, inner, state = setup
    grads = _grads(params, rng)
    want_u, want_s = _update(inner, grads, state, params)
    assert not _zero(want_u)
    for tx in (skip_nonfinite(inner), guard_steps(inner, 10.0 * _norm(grads))):
        u, s = _update(tx, grads, state, params, loss=jnp.float32(0.7))
        assert_tree_equal(u, want_u)
        assert_tree_equal(s, want_s)


@pytest.mark.parametrize("where", ["gradient", "loss"])
def test_nonfinite_is_skipped_and_the_schedule_stays(setup, rng, where):
    params, inner, state = setup
    grads = _grads(params, rng)
    loss = jnp.float32(0.7)
    if where == "gradient":
        leaf = jax.tree.leaves(grads)[1]
        grads = jax.tree.map(lambda g: g.at[(0,) * g.ndim].set(jnp.nan) if g is leaf else g, grads)
    else:
        loss = jnp.float32(jnp.inf)  # finite gradients, non-finite loss: still skipped
    for tx in (skip_nonfinite(inner), guard_steps(inner, 1e-3)):  # also when the norm is "too large"
        u, s = _update(tx, grads, state, params, loss=loss)
        assert _zero(u)
        assert_tree_equal(s, state)
        assert int(schedule_count(s)) == int(schedule_count(state))  # pyright: ignore[reportArgumentType] -- this optimizer state has a schedule count


def test_too_large_is_skipped_and_only_the_schedule_advances(setup, rng):
    params, inner, state = setup
    grads = _grads(params, rng, scale=100.0)
    limit = 0.5 * _norm(grads)
    tx = guard_steps(inner, limit)
    u, s = _update(tx, grads, state, params, loss=jnp.float32(3.0))
    assert _zero(u)
    assert int(schedule_count(s)) == int(schedule_count(state)) + 1  # pyright: ignore[reportArgumentType] -- this optimizer state has a schedule count
    adam, adam0 = s[1][0], state[1][0]  # pyright: ignore[reportIndexIssue] -- an optax state is typed as any pytree; this one is the (named) tuple its transformation builds
    assert_tree_equal((adam.mu, adam.nu, adam.count), (adam0.mu, adam0.nu, adam0.count))  # pyright: ignore[reportAttributeAccessIssue] -- an optax state is typed as any pytree; this one is the (named) tuple its transformation builds
    # just under the limit: the inner update, as is
    small = jax.tree.map(lambda g: g * (0.99 * limit / _norm(grads)), grads)
    u, s = _update(tx, small, state, params, loss=jnp.float32(3.0))
    want_u, want_s = _update(inner, small, state, params)
    assert_tree_equal(u, want_u)
    assert_tree_equal(s, want_s)


def test_guards_around_the_spike_guard_keep_its_running_mean(key, rng):
    """The spike guard (inside the optimizer) is neither fed a skipped step's norm nor counts it."""
    params = toy_params(key)
    inner = make_optimizer(dataclasses.replace(CFG, spike_factor=10.0))
    state = _update(inner, _grads(params, rng), inner.init(params), params)[1]
    tx = guard_steps(inner, 1.0)
    _, s = _update(tx, _grads(params, rng, scale=100.0), state, params, loss=jnp.float32(1.0))
    assert (float(s.log_norm_ema), int(s.seen)) == (float(state.log_norm_ema), int(state.seen))  # pyright: ignore[reportAttributeAccessIssue] -- an optax state is typed as any pytree; this one is the (named) tuple its transformation builds
    assert int(schedule_count(s)) == int(schedule_count(state)) + 1  # pyright: ignore[reportArgumentType] -- this optimizer state has a schedule count


def test_skip_reasons():
    nan, inf = jnp.float32(jnp.nan), jnp.float32(jnp.inf)
    cases = [
        ((1.0, 2.0, None), (False, False)),
        ((1.0, 2.0, 1.5), (False, True)),
        ((1.0, 2.0, 2.5), (False, False)),
        ((nan, 2.0, 1.5), (True, False)),
        ((1.0, inf, 1.5), (True, False)),
        ((None, nan, None), (True, False)),
    ]
    for (loss, norm, limit), want in cases:
        got = skip_reasons(None if loss is None else jnp.float32(loss), jnp.float32(norm), limit)
        assert tuple(bool(x) for x in got) == want, (loss, norm, limit)
    with pytest.raises(ValueError, match="max_norm=0"):
        skip_large_gradients(optax.sgd(1.0), 0)
