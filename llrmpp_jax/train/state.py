"""The training state: everything a resumed run needs besides the data position.

``rng`` holds the raw data of the run's base PRNG key; the key of step ``s`` on device
``i`` is ``fold_in(fold_in(base, s), i)`` (see :func:`step_key`), so a resumed run draws
the same randomness as an uninterrupted one without storing any per-step key.
"""

from __future__ import annotations

from typing import Any, no_type_check

import jax
import jax.numpy as jnp
import optax
from flax import struct

from llrmpp_jax.array_typing import Array, Int, KeyArray, UInt32


# Not checked: a pytree, so JAX rebuilds it around whatever a transform carries in its
# leaves (per-device copies, host arrays, shapes, shardings); the annotations say what one
# device's state holds.
@no_type_check
@struct.dataclass
class TrainState:
    """Pytree of the run's state (a leaf per array; replicated over data-parallel devices).

    ``step``: train steps taken, applied or skipped (int32 ``[]``).
    ``params``: float32 parameter pytree. ``opt_state``: optax state (float32 moments).
    ``skipped``: steps whose update was skipped because the loss or gradient norm was
    not finite or the norm exceeded the step's guard (int32 ``[]``). ``rng``: base key data (uint32 ``[2]`` for
    threefry).
    """

    step: Int[Array, ""]
    params: Any
    opt_state: optax.OptState
    skipped: Int[Array, ""]
    rng: UInt32[Array, " 2"]


def _check_float32(params) -> None:
    """Raise if a floating parameter is not float32 (params and optimizer stay fp32)."""
    for path, leaf in jax.tree_util.tree_flatten_with_path(params)[0]:
        dtype = jnp.result_type(leaf)
        if jnp.issubdtype(dtype, jnp.floating) and dtype != jnp.float32:
            raise ValueError(
                f"init_train_state: params{jax.tree_util.keystr(path)} has dtype {dtype}; "
                f"parameters must be float32 (bf16 compute casts them inside the loss)"
            )


def init_train_state(params: Any, optimizer: optax.GradientTransformation, key: KeyArray) -> TrainState:
    """Fresh state at step 0: ``optimizer.init(params)`` and ``key`` as the base key.

    ``key`` must be a typed key (``jax.random.key``) of the default implementation, not
    legacy uint32 key data.
    """
    if not (hasattr(key, "dtype") and jnp.issubdtype(key.dtype, jax.dtypes.prng_key)):
        raise ValueError(
            f"init_train_state: key must be a typed PRNG key from jax.random.key(...), got "
            f"{getattr(key, 'dtype', type(key))} with shape {jnp.shape(key)}"
        )
    if key.shape != ():
        raise ValueError(f"init_train_state: key has shape {key.shape}, expected ()")
    impl = str(jax.random.key_impl(key))
    if impl != jax.config.jax_default_prng_impl:  # pyright: ignore[reportAttributeAccessIssue] -- jax.config's options are made at run time; its stub lists none
        # step_key re-wraps the stored key data with the default implementation.
        raise ValueError(
            f"init_train_state: key uses the PRNG implementation {impl!r}, expected the "
            f"default {jax.config.jax_default_prng_impl!r}"  # pyright: ignore[reportAttributeAccessIssue] -- jax.config's options are made at run time; its stub lists none
        )
    _check_float32(params)
    return TrainState(
        step=jnp.zeros((), jnp.int32),
        params=params,
        opt_state=optimizer.init(params),
        skipped=jnp.zeros((), jnp.int32),
        rng=jax.random.key_data(key),
    )


def step_key(state: TrainState, device_index: Int[Array, ""] | int) -> KeyArray:
    """The PRNG key of ``state.step`` on data-parallel device ``device_index``."""
    base = jax.random.wrap_key_data(state.rng)
    return jax.random.fold_in(jax.random.fold_in(base, state.step), device_index)
