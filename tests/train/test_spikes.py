"""skip_gradient_spikes against its inner optimizer run on the accepted gradients only."""

import jax
import jax.numpy as jnp
import numpy as np
import optax
import pytest

from llrmpp_jax.train import OptimizerConfig, make_optimizer
from llrmpp_jax.train.spikes import skip_gradient_spikes


def _gradients(rng, steps: int, spikes: dict[int, float], shift_at: int | None = None, shift: float = 1.0):
    """Random gradients of norm ~0.03 (the ablation scale's), times ``spikes[t]`` at step t,
    and times ``shift`` from ``shift_at`` on."""
    out = []
    for t in range(steps):
        g = {"w": rng.normal(size=(4, 3)) * 0.01, "b": rng.normal(size=(3,)) * 0.01}
        m = spikes.get(t, 1.0) * (shift if shift_at is not None and t >= shift_at else 1.0)
        out.append(jax.tree.map(lambda x: jnp.asarray(x * m, jnp.float32), g))  # noqa: B023  mapped here
    return out


def _run(opt, params, grads):
    state = opt.init(params)
    ups = []
    for g in grads:
        with jax.numpy_dtype_promotion("standard"):
            u, state = opt.update(g, state, params)
        ups.append(u)
    return ups, state


def test_spikes_are_skipped_and_the_rest_is_the_inner_optimizer(rng):
    inner = optax.adamw(1e-2, b1=0.9, b2=0.95)
    params = {"w": jnp.asarray(rng.normal(size=(4, 3)), jnp.float32), "b": jnp.zeros((3,), jnp.float32)}
    spikes = {40: 3000.0, 55: 200.0, 70: 60.0, 5: 500.0}  # step 5 is inside the warmup: applied
    grads = _gradients(rng, 90, spikes)
    ups, state = _run(skip_gradient_spikes(inner, factor=10.0, warmup=20), params, grads)
    skipped = {40, 55, 70}
    expected, _ = _run(inner, params, [g for t, g in enumerate(grads) if t not in skipped])
    it = iter(expected)
    for t, u in enumerate(ups):
        if t in skipped:
            assert all(float(jnp.abs(x).max()) == 0.0 for x in jax.tree.leaves(u)), t
        else:
            jax.tree.map(lambda a, b: np.testing.assert_allclose(a, b, rtol=1e-6, atol=1e-9), u, next(it))
    assert int(state.spikes) == 3 and int(state.seen) == 90  # pyright: ignore[reportAttributeAccessIssue] -- an optax state is typed as any pytree; this one is the (named) tuple its transformation builds


def test_a_lasting_rise_is_accepted_after_the_predicted_steps(rng):
    inner = optax.sgd(1.0)
    params = {"w": jnp.zeros((4, 3), jnp.float32), "b": jnp.zeros((3,), jnp.float32)}
    grads = _gradients(rng, 100, {}, shift_at=50, shift=100.0)
    ups, state = _run(skip_gradient_spikes(inner, factor=10.0, decay=0.95, warmup=20), params, grads)
    zero = [t for t, u in enumerate(ups) if float(jnp.abs(u["w"]).max()) == 0.0]
    # log(100 / 10) / (0.05 log 10) = 20 skipped steps, give or take the noise of the norms
    # (near the end, a step just under the threshold may pass between skipped ones).
    assert zero[:15] == list(range(50, 65)) and 15 <= len(zero) <= 25 and max(zero) < 77, zero
    assert int(state.spikes) == len(zero)  # pyright: ignore[reportAttributeAccessIssue] -- an optax state is typed as any pytree; this one is the (named) tuple its transformation builds


@pytest.mark.parametrize(
    "kwargs, message",
    [
        ({"factor": 1.0}, "skip_gradient_spikes: factor=1.0 must be > 1"),
        ({"decay": 1.0}, "skip_gradient_spikes: decay=1.0 must be in (0, 1)"),
    ],
)
def test_bad_settings_are_one_line(kwargs, message):
    with pytest.raises(ValueError) as err:
        skip_gradient_spikes(optax.sgd(1.0), **kwargs)
    assert str(err.value) == message


def test_optimizer_config_wraps_and_keeps_the_schedule_count_readable():
    from llrmpp_jax.train.optimizer import schedule_count

    opt = make_optimizer(OptimizerConfig(warmup_steps=1, total_steps=10, spike_factor=10.0))
    params = {"w": jnp.ones((2, 2), jnp.float32)}
    state = opt.init(params)
    with jax.numpy_dtype_promotion("standard"):
        _, state = opt.update({"w": jnp.full((2, 2), 0.5, jnp.float32)}, state, params)
    assert int(schedule_count(state)) == 1  # pyright: ignore[reportArgumentType] -- this optimizer state has a schedule count
