"""Attention as plain dense float64 NumPy: an explicit softmax over all L keys, written
independently of the library, and the whole ``Attention`` (or ``LocalAttention``) module
recomputed from its parameters; with the helpers that draw fresh parameters and measure
the relative error. The tests of ``nn/attention.py``, ``nn/local_attention.py`` and
``nn/transformer.py`` use them."""

import math

import jax
import jax.numpy as jnp
import numpy as np
from scipy.special import erf


def softmax(x: np.ndarray) -> np.ndarray:
    e = np.exp(x - x.max(axis=-1, keepdims=True))
    return e / e.sum(axis=-1, keepdims=True)


def gelu(x: np.ndarray) -> np.ndarray:
    return 0.5 * x * (1.0 + erf(x / math.sqrt(2.0)))


def rms(x: np.ndarray, scale: np.ndarray, eps: float = 1e-5) -> np.ndarray:
    return x / np.sqrt(np.mean(x * x, axis=-1, keepdims=True) + eps) * scale


def dense_attention(q, k, v, bias=None, mask=None):
    """``[B, Lq, nh, hd]`` queries against all keys; bias/mask broadcast to ``[B, nh, Lq, Lk]``."""
    logits = np.einsum("bqhd,bkhd->bhqk", q, k) / math.sqrt(q.shape[-1])
    if bias is not None:
        logits = logits + bias
    if mask is not None:
        logits = np.where(mask, logits, -np.inf)
    return np.einsum("bhqk,bkhd->bqhd", softmax(logits), v)


def attention_module_oracle(p, x, head_dim, qk_norm, mask_bias=None, eps=1e-5):
    """Float64 re-computation of Attention (or LocalAttention) from its params ``p``.

    ``mask_bias(p) -> (mask [L, L], bias [nh, L, L])`` restricts and biases the logits
    (``tests/oracles/local_attention.py``'s dense k-NN oracle); None: plain global attention.
    """
    p = jax.tree.map(lambda a: np.asarray(a, np.float64), p)
    x = np.asarray(x, np.float64)
    b, n, d = x.shape
    nh = d // head_dim
    qkv = (x @ p["qkv"]["kernel"]).reshape(b, n, 3, nh, head_dim)
    q, k, v = qkv[:, :, 0], qkv[:, :, 1], qkv[:, :, 2]
    if qk_norm:
        q, k = rms(q, p["q_norm"]["scale"], eps), rms(k, p["k_norm"]["scale"], eps)
    bias = mask = None
    if mask_bias is not None:
        mask, bias = mask_bias(p)
        mask, bias = mask[None, None], bias[None]
    o = dense_attention(q, k, v, bias, mask)
    return o.reshape(b, n, d) @ p["proj"]["kernel"]


def randomize(params, rng, std=0.3):
    """Replace every param by fresh non-trivial values (norm scales around 1)."""

    def new(path, a):
        name = jax.tree_util.keystr(path)
        vals = rng.normal(size=a.shape)
        vals = 1.0 + 0.2 * vals if "scale" in name else std * vals
        return jnp.asarray(vals, a.dtype)

    return jax.tree_util.tree_map_with_path(new, params)


def rel_err(got, want) -> float:
    return float(np.max(np.abs(np.asarray(got, np.float64) - want)) / np.max(np.abs(want)))
