"""Normalisation layers: pure functions (computed in at least float32, cast back) and
the thin Flax modules that hold their ``scale``.

Both follow the PyTorch modules Long-LRM uses: ``nn.LayerNorm(dim, bias=False)`` and
mamba_ssm's ``RMSNorm`` (weight only), eps 1e-5 by default.
"""

import flax.linen as nn
import jax
import jax.numpy as jnp

from llrmpp_jax.array_typing import Array, ArrayLike, Float


def _compute_dtype(x: ArrayLike) -> jnp.dtype:
    # bf16 activations are normalised in float32; float64 (test oracles) stays float64.
    return jnp.dtype(jnp.float64) if x.dtype == jnp.float64 else jnp.dtype(jnp.float32)


def _lead(scale: ArrayLike, x: ArrayLike) -> ArrayLike:
    """Give ``scale [C]`` the rank of ``x`` (rank promotion is an error in our tests)."""
    return scale.reshape((1,) * (x.ndim - 1) + scale.shape)


def rms_norm(x: Float[ArrayLike, "... C"], scale: Float[ArrayLike, " C"], eps: float = 1e-5) -> Float[Array, "... C"]:
    """``x / sqrt(mean(x**2) + eps) * scale`` over the last axis."""
    xf = x.astype(_compute_dtype(x))
    inv = jax.lax.rsqrt(jnp.mean(jnp.square(xf), axis=-1, keepdims=True) + eps)
    return (xf * inv * _lead(scale.astype(xf.dtype), xf)).astype(x.dtype)  # pyright: ignore[reportReturnType] -- jnp operations give a jax.Array; the ArrayLike input type carries through


def layer_norm(x: Float[ArrayLike, "... C"], scale: Float[ArrayLike, " C"], eps: float = 1e-5) -> Float[Array, "... C"]:
    """LayerNorm without bias over the last axis (biased variance, as PyTorch)."""
    xf = x.astype(_compute_dtype(x))
    mean = jnp.mean(xf, axis=-1, keepdims=True)
    var = jnp.mean(jnp.square(xf - mean), axis=-1, keepdims=True)
    return ((xf - mean) * jax.lax.rsqrt(var + eps) * _lead(scale.astype(xf.dtype), xf)).astype(x.dtype)  # pyright: ignore[reportReturnType] -- jnp operations give a jax.Array; the ArrayLike input type carries through


class LayerNorm(nn.Module):
    """Holds the ``scale`` of :func:`layer_norm` (no bias) over the last axis."""

    eps: float = 1e-5

    @nn.compact
    def __call__(self, x: Float[ArrayLike, "... C"]) -> Float[Array, "... C"]:
        return layer_norm(x, self.param("scale", nn.initializers.ones, (x.shape[-1],), jnp.float32), self.eps)


class RMSNorm(nn.Module):
    """Holds the ``scale`` of :func:`rms_norm` over the last axis."""

    eps: float = 1e-5

    @nn.compact
    def __call__(self, x: Float[ArrayLike, "... C"]) -> Float[Array, "... C"]:
        return rms_norm(x, self.param("scale", nn.initializers.ones, (x.shape[-1],), jnp.float32), self.eps)
