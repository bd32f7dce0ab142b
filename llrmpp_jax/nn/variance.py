"""Device variance of loop carries under ``shard_map`` (its varying-manual-axes typing).

Inside ``jax.shard_map`` every array is typed as varying or invariant over the mesh axes. A
``lax.scan`` carry must have the same type in and out, and a ``custom_vjp`` must return
each cotangent with its primal's type. A carry started from ``jnp.zeros`` is invariant and
becomes varying as soon as per-device data (a batch shard) flows into it, which
``lax.scan`` rejects. These helpers build carries and align inputs from the data itself, so
the same code runs inside and outside ``shard_map`` (where both are no-ops).
"""

from __future__ import annotations

import jax.numpy as jnp
from jax import lax

from llrmpp_jax.array_typing import Array, ArrayLike


def full_like_varying(ref: Array, shape: tuple[int, ...], value: float, dtype) -> Array:
    """``jnp.full(shape, value, dtype)`` with ``ref``'s device variance."""
    return lax.full_like(ref, value, dtype, shape)


def common_variance(*xs: ArrayLike | None) -> list[Array | None]:
    """``xs`` made varying over the union of their varying axes (``None`` passes through).

    Before a ``custom_vjp``: a replicated input (a parameter-made bias) beside per-device
    q must enter with q's variance, so that autodiff (the transpose of the implicit cast)
    sums its cotangent over devices instead of the rule returning a mistyped one."""
    zero = sum(lax.full_like(x, 0, jnp.float32, ()) for x in xs if x is not None)
    return [None if x is None else x + zero.astype(x.dtype) for x in xs]  # pyright: ignore[reportAttributeAccessIssue, reportReturnType] -- only arrays get here (None is kept)
