"""The train step's guards as optax wrappers: each one returns zero updates where it skips
one and keeps (or moves on) its inner optimizer's state, like ``optax.apply_if_finite``.

* :func:`skip_nonfinite`: a non-finite loss or gradient norm (Long-LRM's guard, reference
  facts §2.1): inner state bitwise unchanged, its schedule does not advance. Stateless.
* :func:`skip_large_gradients`: a finite gradient norm above an absolute threshold
  (Long-LRM's ``grad_clip_norm * allowed_gradnorm_factor`` = 50): Adam moments unchanged,
  the learning-rate schedule one step further (Long-LRM still calls ``scheduler.step()``).
  Stateless.
* :func:`~llrmpp_jax.train.spikes.skip_gradient_spikes`: a gradient norm far above the
  recent norms (inside the optimizer, ``OptimizerConfig.spike_factor``).

:func:`~llrmpp_jax.train.step.make_train_step` composes the first two around its optimizer
(which may hold the third) with :func:`guard_steps` and reads why a step was skipped from
:func:`skip_reasons`, the guards' own test. Being stateless, they leave the optimizer
state's structure as it is, so a checkpoint written before they were wrappers restores.
"""

from __future__ import annotations

from typing import Any

import jax
import jax.numpy as jnp
import optax

from llrmpp_jax.array_typing import Array, ArrayLike, Bool, Float
from llrmpp_jax.train.optimizer import advance_schedule


def skip_reasons(
    loss: Float[ArrayLike, ""] | None, grad_norm: Float[ArrayLike, ""], max_norm: float | None
) -> tuple[Bool[Array, ""], Bool[Array, ""]]:
    """``(nonfinite, too_large)`` of one step: the loss (None: not checked) or the gradient's
    global norm is not finite; the norm is finite and above ``max_norm`` (None: never).
    The test :func:`skip_nonfinite` and :func:`skip_large_gradients` apply."""
    finite = jnp.isfinite(grad_norm)
    if loss is not None:
        finite = finite & jnp.isfinite(loss)
    too_large = finite & (grad_norm > max_norm) if max_norm is not None else jnp.zeros((), jnp.bool_)
    return ~finite, too_large


def _skip_if(skip: Bool[Array, ""], updates: Any, new_state: Any, kept_state: Any) -> tuple[Any, Any]:
    """``(zero updates, kept_state)`` where ``skip``, else ``(updates, new_state)``."""
    out = jax.tree.map(lambda u: jnp.where(skip, jnp.zeros_like(u), u), updates)
    return out, jax.tree.map(lambda new, old: jnp.where(skip, old, new), new_state, kept_state)


def skip_nonfinite(inner: optax.GradientTransformation) -> optax.GradientTransformationExtraArgs:
    """``inner``, except that an update whose gradient global norm, or the ``loss`` passed as
    an extra argument (``update(grads, state, params, loss=loss)``), is not finite is skipped:
    zero updates, ``inner``'s state bitwise unchanged (its schedule stays). Stateless: the
    state is ``inner``'s. Other extra arguments go on to ``inner``."""
    inner = optax.with_extra_args_support(inner)

    def update(updates, state, params=None, *, loss=None, **extra):
        nonfinite, _ = skip_reasons(loss, optax.tree.norm(updates).astype(jnp.float32), None)
        new_updates, new_state = inner.update(updates, state, params, **extra)
        return _skip_if(nonfinite, new_updates, new_state, state)

    return optax.GradientTransformationExtraArgs(inner.init, update)


def skip_large_gradients(inner: optax.GradientTransformation, max_norm: float) -> optax.GradientTransformationExtraArgs:
    """``inner``, except that an update whose gradient global norm is finite and above
    ``max_norm`` is skipped: zero updates, ``inner``'s state unchanged but for its
    learning-rate schedules, one step further
    (:func:`~llrmpp_jax.train.optimizer.advance_schedule`). Stateless."""
    if not max_norm > 0:
        raise ValueError(f"skip_large_gradients: max_norm={max_norm} must be > 0")
    inner = optax.with_extra_args_support(inner)

    def update(updates, state, params=None, **extra):
        _, too_large = skip_reasons(None, optax.tree.norm(updates).astype(jnp.float32), max_norm)
        new_updates, new_state = inner.update(updates, state, params, **extra)
        return _skip_if(too_large, new_updates, new_state, advance_schedule(state))

    return optax.GradientTransformationExtraArgs(inner.init, update)


def guard_steps(
    optimizer: optax.GradientTransformation, skip_grad_norm_above: float | None = None
) -> optax.GradientTransformationExtraArgs:
    """The train step's guards around ``optimizer``: :func:`skip_nonfinite` outside
    :func:`skip_large_gradients` (when ``skip_grad_norm_above`` is set), so a non-finite
    step never advances the schedule. The state is ``optimizer``'s."""
    inner = optimizer if skip_grad_norm_above is None else skip_large_gradients(optimizer, skip_grad_norm_above)
    return skip_nonfinite(inner)
