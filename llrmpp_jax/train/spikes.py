"""Skipping gradient spikes relative to the recent gradient norm: :func:`skip_gradient_spikes`.

Why: one gradient whose norm is hundreds of times the usual one fills Adam's second-moment
estimate ``v`` for the parameters it touches; with ``b2 = 0.95`` their updates then stay
~``spike / usual`` times too small for ``log(spike / usual) / (1 - b2)`` steps, and a short
run stalls. Long-LRM's guards are absolute (clip at norm 10, skip above 50), sized for its
model and data; at the ablation notebooks' cpu scale the usual norm is hundreds of times
smaller than those thresholds, so a spike thousands of times the usual norm is clipped to 10
and applied, and one tens to hundreds of times it passes untouched (the stalled seeds' norms:
``notebooks/README.md``, "Stalled seeds", and ``docs/lab-notes.md``).
"""

from __future__ import annotations

import math
from typing import NamedTuple

import jax
import jax.numpy as jnp
import optax

from llrmpp_jax.array_typing import Array, Float, Int


class SpikeGuardState(NamedTuple):
    """``inner``: the wrapped optimizer's state; ``log_norm_ema``: exponential moving
    average of the log gradient norm (not bias-corrected); ``seen``: finite gradients
    seen; ``spikes``: updates skipped as spikes."""

    inner: optax.OptState
    log_norm_ema: Float[Array, ""]
    seen: Int[Array, ""]
    spikes: Int[Array, ""]


def skip_gradient_spikes(
    inner: optax.GradientTransformation, factor: float = 10.0, decay: float = 0.95, warmup: int = 20
) -> optax.GradientTransformation:
    """``inner``, except that an update whose gradient's global norm exceeds ``factor`` times
    the running (geometric) mean of recent norms is skipped: zero updates, ``inner``'s state
    bitwise unchanged (its schedule does not advance), ``spikes`` incremented.

    The running mean is an exponential moving average of ``log(norm)`` with ``decay``,
    bias-corrected, over every finite gradient, each entering at most at ``log(factor)``
    above the current mean: a spike moves it a little, and a lasting rise of the norm by
    ``r > factor`` is accepted after about ``log(r / factor) / ((1 - decay) log(factor))``
    steps (10 for r = 30, 20 for r = 100 at the defaults) instead of being skipped forever. Nothing is skipped
    during the first ``warmup`` gradients, whose norms fall fast. Non-finite gradients are left to the train
    step's guard outside it (:func:`~llrmpp_jax.train.guards.skip_nonfinite`; they do not enter the mean).
    """
    if factor <= 1.0:
        raise ValueError(f"skip_gradient_spikes: factor={factor} must be > 1")
    if not 0.0 < decay < 1.0:
        raise ValueError(f"skip_gradient_spikes: decay={decay} must be in (0, 1)")
    log_factor = math.log(factor)

    def init(params) -> SpikeGuardState:
        zero = jnp.zeros((), jnp.int32)
        return SpikeGuardState(inner.init(params), jnp.zeros((), jnp.float32), zero, zero)

    def update(updates, state: SpikeGuardState, params=None):
        log_norm = jnp.log(optax.tree.norm(updates).astype(jnp.float32))
        finite = jnp.isfinite(log_norm)
        # Bias-corrected mean of the log norms seen so far (0 before the first).
        correction = 1.0 - jnp.float32(decay) ** state.seen.astype(jnp.float32)
        mean = jnp.where(state.seen > 0, state.log_norm_ema / jnp.maximum(correction, 1e-12), 0.0)
        spike = finite & (state.seen >= warmup) & (log_norm > mean + log_factor)
        entered = jnp.where(state.seen > 0, jnp.minimum(log_norm, mean + log_factor), log_norm)
        ema = jnp.where(finite, decay * state.log_norm_ema + (1.0 - decay) * entered, state.log_norm_ema)
        new_updates, new_inner = inner.update(updates, state.inner, params)
        out = jax.tree.map(lambda u: jnp.where(spike, jnp.zeros_like(u), u), new_updates)
        kept_inner = jax.tree.map(lambda new, old: jnp.where(spike, old, new), new_inner, state.inner)
        return out, SpikeGuardState(
            kept_inner, ema, state.seen + finite.astype(jnp.int32), state.spikes + spike.astype(jnp.int32)
        )

    return optax.GradientTransformation(init, update)  # pyright: ignore[reportArgumentType] -- optax's update takes params=None; the stub's protocol is stricter
