"""Local attention of the Long-LRM++ decoder (paper §3.3): every token attends to its k nearest tokens.

Neighbourhoods. On an ``h x w`` token grid (row-major), token ``t`` attends to exactly
``kn = min(k, h*w)`` in-grid tokens: the ``kn`` nearest in Euclidean distance (token
units), ties broken by ``dy`` and then ``dx`` (both ascending, ``(dy, dx)`` = neighbour
minus token). The self offset ``(0, 0)`` always comes first. A token whose ``k`` nearest
offsets all fit inside the grid (an *interior* token) gets the same ordered offset set as
every other interior token, so the layer is translation invariant there; a border token
attends to its ``kn`` nearest in-grid tokens instead (nothing is masked). The tables are NumPy,
built once per ``(h, w, k)`` at trace time, so shapes stay static under ``jit``.

Relative position (AutoFocusFormer, facts §6.3): the logit of neighbour ``j`` gets
``MLP(dx, dy, |d|, dx/|d|, dy/|d|)`` of its true offset (0 features for the self offset).
The MLP runs once per call on the distinct offsets used on the grid (221 for k = 64 on a
32x32 grid) and the per-token biases are gathered from that table.

Parameter names mirror :class:`~llrmpp_jax.nn.attention.Attention` (``qkv``, ``proj``,
``q_norm``, ``k_norm``) plus ``rel_bias``.
"""

from __future__ import annotations

import functools
import math

import flax.linen as nn
import jax
import jax.numpy as jnp
import numpy as np
from jax import lax

from llrmpp_jax.array_typing import Array, ArrayLike, DTypeLike, Float, Int
from llrmpp_jax.nn.attention import _check_width, _num_heads, _out_proj, _qkv_heads
from llrmpp_jax.nn.initializers import DENSE_INIT
from llrmpp_jax.nn.variance import common_variance, full_like_varying


def _window_radius(h: int, w: int, kn: int) -> int:
    """A distance bound on every token's ``kn`` nearest in-grid tokens (as an integer floor).

    Any ``a`` consecutive rows and ``b`` consecutive columns (``a <= h``, ``b <= w``,
    ``a*b >= kn``) that contain a token hold ``kn`` in-grid tokens within distance
    ``sqrt((a-1)^2 + (b-1)^2)`` of it, so its ``kn`` nearest lie within that distance.
    """
    a = min(h, math.ceil(math.sqrt(kn)))
    b = -(-kn // a)
    if b > w:
        b, a = w, -(-kn // w)
    return math.isqrt((a - 1) ** 2 + (b - 1) ** 2)


@functools.lru_cache(maxsize=64)
def neighbour_table(h: int, w: int, k: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Static k-nearest-neighbour table of an ``h x w`` token grid (NumPy, module doc's rule).

    Returns, with ``L = h*w`` and ``kn = min(k, L)``:
      index: ``[L, kn]`` int32, row-major index of token ``t``'s ``j``-th nearest token.
      offset_id: ``[L, kn]`` int32, row of ``offsets`` holding that neighbour's offset.
      offsets: ``[U, 2]`` int32, the distinct ``(dy, dx)`` offsets used by any token, in
        tie-rule order, so ``offsets[:kn]`` is the interior offset set and an interior
        token's ``offset_id`` row is ``0 .. kn-1``.
    The arrays are cached and read-only.
    """
    if h < 1 or w < 1 or k < 1:
        raise ValueError(f"neighbour_table: h, w, k must be >= 1, got h={h}, w={w}, k={k}")
    n = h * w
    kn = min(k, n)
    r = _window_radius(h, w, kn)
    dy, dx = (
        a.ravel()
        for a in np.meshgrid(
            np.arange(-min(h - 1, r), min(h - 1, r) + 1), np.arange(-min(w - 1, r), min(w - 1, r) + 1), indexing="ij"
        )
    )
    order = np.lexsort((dx, dy, dy * dy + dx * dx))
    cand = np.stack([dy[order], dx[order]], axis=-1)  # [C, 2], tie-rule order
    ty, tx = np.divmod(np.arange(n), w)
    ny = ty[:, None] + cand[None, :, 0]
    nx = tx[:, None] + cand[None, :, 1]
    inside = (ny >= 0) & (ny < h) & (nx >= 0) & (nx < w)  # [L, C]
    assert inside.sum(axis=1).min() >= kn, "window bound too small"  # _window_radius guarantees it
    first = np.argsort(~inside, axis=1, kind="stable")[:, :kn]  # the first kn in-grid candidates
    rows = np.arange(n)[:, None]
    index = (ny * w + nx)[rows, first].astype(np.int32)
    used = np.unique(first)
    offset_id = np.searchsorted(used, first).astype(np.int32)
    offsets = cand[used].astype(np.int32)
    for a in (index, offset_id, offsets):
        a.setflags(write=False)
    return index, offset_id, offsets


def relative_position_features(offsets: Int[np.ndarray, "U 2"]) -> Float[np.ndarray, "U 5"]:
    """Bias-MLP input per offset: ``(dx, dy, |d|, dx/|d|, dy/|d|)``, all 0 for ``(0, 0)``.

    ``offsets`` is ``[U, 2]`` ``(dy, dx)`` in token-grid units (as :func:`neighbour_table`).
    Returns ``[U, 5]`` float32 (NumPy, static).
    """
    offsets = np.asarray(offsets)
    if offsets.ndim != 2 or offsets.shape[1] != 2:
        raise ValueError(f"relative_position_features: offsets must be [k, 2] (dy, dx), got shape {offsets.shape}")
    dy, dx = offsets[:, 0].astype(np.float64), offsets[:, 1].astype(np.float64)
    dist = np.hypot(dx, dy)
    safe = np.where(dist > 0, dist, 1.0)
    feats = np.stack([dx, dy, dist, dx / safe, dy / safe], axis=-1)
    return feats.astype(np.float32)


def _accumulator(dtype) -> jnp.dtype:
    """Logits, softmax and gradients run in ``promote(dtype, float32)``."""
    return jnp.dtype(dtype) if jnp.finfo(dtype).bits > 32 else jnp.dtype(jnp.float32)


def _forward(q, k, v, index, bias):
    """``[B, L, nh, hd]`` inputs -> (output ``[B, L, nh, hd]``, weights ``[kn, B, L, nh]``)."""
    acc = _accumulator(q.dtype)
    scale = jnp.asarray(q.shape[-1] ** -0.5, acc)

    def logit(_, xs):  # neighbour slot j: one [B, L, nh, hd] gather
        idx, b = xs
        kj = jnp.take(k, idx, axis=1, mode="clip")  # idx is in range; "clip" skips the fill
        s = jnp.einsum("blhd,blhd->blh", q, kj, preferred_element_type=acc)
        return None, s * scale + b.astype(acc)[None]

    _, logits = lax.scan(logit, None, (index.T, jnp.swapaxes(bias, 0, 1)))
    weights = jax.nn.softmax(logits, axis=0)

    def mix(out, xs):
        idx, wj = xs
        return out + wj[..., None] * jnp.take(v, idx, axis=1, mode="clip").astype(acc), None

    out, _ = lax.scan(mix, full_like_varying(weights, v.shape, 0.0, acc), (index.T, weights))
    return out.astype(v.dtype), weights


@jax.custom_vjp
def _knn_attention(q, k, v, index, bias):
    return _forward(q, k, v, index, bias)[0]


def _knn_attention_fwd(q, k, v, index, bias):
    out, weights = _forward(q, k, v, index, bias)
    return out, (q, k, v, index, weights, bias)


def _knn_attention_bwd(res, g):
    """Recomputes each slot's gathers; dk and dv are scatter-adds (a token is the neighbour of
    up to kn tokens, more at borders)."""
    q, k, v, index, weights, bias = res
    acc = weights.dtype
    scale = jnp.asarray(q.shape[-1] ** -0.5, acc)
    g = g.astype(acc)

    def dv_step(dv, xs):
        idx, wj = xs
        vj = jnp.take(v, idx, axis=1, mode="clip")
        dwj = jnp.einsum("blhd,blhd->blh", g, vj, preferred_element_type=acc)
        return dv.at[:, idx].add(wj[..., None] * g), dwj

    dv, dw = lax.scan(dv_step, full_like_varying(g, v.shape, 0.0, acc), (index.T, weights))
    ds = weights * (dw - jnp.sum(weights * dw, axis=0, keepdims=True))  # softmax backward, [kn, B, L, nh]
    qa = q.astype(acc)

    def dqk_step(carry, xs):
        dq, dk = carry
        idx, gj = xs
        kj = jnp.take(k, idx, axis=1, mode="clip").astype(acc)
        return (dq + gj[..., None] * kj, dk.at[:, idx].add(gj[..., None] * qa)), None

    zeros = full_like_varying(ds, q.shape, 0.0, acc)
    (dq, dk), _ = lax.scan(dqk_step, (zeros, zeros), (index.T, ds * scale))
    dbias = jnp.swapaxes(jnp.sum(ds, axis=1), 0, 1)
    return dq.astype(q.dtype), dk.astype(k.dtype), dv.astype(v.dtype), None, dbias.astype(bias.dtype)


_knn_attention.defvjp(_knn_attention_fwd, _knn_attention_bwd)


def local_attention(
    q: Float[Array, "... L nh hd"],
    k: Float[Array, "... L nh hd"],
    v: Float[Array, "... L nh hd"],
    index: Int[Array, "L kn"],
    bias: Float[Array, "L kn nh"],
) -> Float[Array, "... L nh hd"]:
    """Attention of each token over its ``kn`` table neighbours, with a per-pair bias.

    ``out[l] = sum_j softmax_j(q[l].k[index[l, j]] * hd^-0.5 + bias[l, j]) v[index[l, j]]``.
    ``index`` comes from :func:`neighbour_table`; ``bias`` is ``[L, kn, nh]`` (one value per
    token, neighbour and head, shared over the batch).

    Memory: K and V are never gathered for all neighbours at once. A ``lax.scan`` over the
    ``kn`` neighbour slots gathers one ``[..., L, nh, hd]`` slice of K (then of V) per
    step; what lives across steps is the logits/weights ``[kn, ..., L, nh]`` in the
    accumulation dtype (saved for the backward pass) and one ``[..., L, nh, hd]``
    accumulator. The custom VJP recomputes the gathers slot by slot (``dk``/``dv`` by
    scatter-add). Example, one decoder image at the paper's 960x544 target (L = 8160
    tokens, kn = 64, nh*hd = 4*64, float32): weights 8.4 MB, a gathered slice 8.4 MB,
    where gathering K and V whole takes 2 x 535 MB; XLA's temp memory of one fwd+bwd there
    (CPU ``memory_analysis``) is tens of MB instead of gigabytes.
    Logits, softmax and gradients run in ``promote(dtype, float32)`` (bf16 inputs: float32;
    float64: float64); the output has ``v``'s dtype.
    """
    if q.ndim < 3 or q.shape != k.shape or k.shape != v.shape:
        raise ValueError(
            f"local_attention: q, k, v must all be [..., L, nh, hd] of one shape, got "
            f"q {q.shape}, k {k.shape}, v {v.shape}"
        )
    length, nh, hd = q.shape[-3:]
    if index.ndim != 2 or index.shape[0] != length:
        raise ValueError(f"local_attention: index {index.shape} must be [L, kn] with L={length}")
    kn = index.shape[1]
    if bias.shape != (length, kn, nh):
        raise ValueError(f"local_attention: bias has shape {bias.shape}, expected [L, kn, nh] = {(length, kn, nh)}")
    batch = q.shape[:-3]
    flat = lambda a: a.reshape(-1, length, nh, hd)  # noqa: E731
    q, k, v, bias = common_variance(flat(q), flat(k), flat(v), bias)  # pyright: ignore[reportAssignmentType] -- common_variance keeps None only for None inputs
    out = _knn_attention(q, k, v, index, bias)
    return out.reshape(*batch, length, nh, hd)


class RelativePositionBias(nn.Module):
    """``MLP(dx, dy, |d|, dx/|d|, dy/|d|)``: 5 -> ``hidden`` -> GELU (exact) -> ``num_heads``.

    Input ``[U, 5]`` from :func:`relative_position_features`, output ``[U, nh]``.
    ``fc1`` has a bias: the self offset's features are all 0, so without it the self
    bias would be pinned to 0 through the whole MLP. ``fc2`` has none: a per-head
    constant added to every logit cancels in the softmax, so it would be a dead parameter.
    """

    num_heads: int
    hidden: int = 32
    dtype: DTypeLike | None = None

    @nn.compact
    def __call__(self, feats: Float[Array, "U 5"]) -> Float[Array, "U nh"]:
        y = nn.Dense(self.hidden, kernel_init=DENSE_INIT, dtype=self.dtype, name="fc1")(feats)
        y = nn.gelu(y, approximate=False)
        return nn.Dense(self.num_heads, use_bias=False, kernel_init=DENSE_INIT, dtype=self.dtype, name="fc2")(y)


class LocalAttention(nn.Module):
    """k-nearest-neighbour attention on an ``h x w`` grid: ``[..., h*w, D] -> [..., h*w, D]``.

    Tokens are row-major over ``grid = (h, w)``. Params: ``qkv/kernel [D, 3D]``,
    ``proj/kernel [D, D]``, with ``qk_norm`` ``q_norm/scale``, ``k_norm/scale`` (as
    :class:`~llrmpp_jax.nn.attention.Attention`), plus ``rel_bias/fc1/{kernel,bias}``,
    ``rel_bias/fc2/kernel``. The neighbour table is static (built once per trace from
    ``grid`` and ``num_neighbours``); the bias MLP runs once per call on the grid's
    distinct offsets. See :func:`local_attention` for memory.
    """

    dim: int
    head_dim: int
    qk_norm: bool
    grid: tuple[int, int]
    num_neighbours: int = 64
    bias_hidden: int = 32
    norm_eps: float = 1e-5
    dtype: DTypeLike | None = None

    @nn.compact
    def __call__(self, x: Float[ArrayLike, "... L D"]) -> Float[Array, "... L D"]:
        nh = _num_heads(self.dim, self.head_dim, "LocalAttention")
        _check_width(x, self.dim, "LocalAttention")
        h, w = self.grid
        if x.shape[-2] != h * w:
            raise ValueError(
                f"LocalAttention: x has shape {x.shape}, expected [..., h*w, D] with "
                f"h*w = {h}*{w} = {h * w} tokens for grid {self.grid}"
            )
        index, offset_id, offsets = neighbour_table(h, w, self.num_neighbours)
        table = RelativePositionBias(nh, self.bias_hidden, self.dtype, name="rel_bias")(
            jnp.asarray(relative_position_features(offsets))
        )
        bias = jnp.take(table, jnp.asarray(offset_id), axis=0)  # [L, kn, nh]
        q, k, v = _qkv_heads(x, self.dim, self.head_dim, self.qk_norm, self.norm_eps, self.dtype)
        o = local_attention(q, k, v, jnp.asarray(index), bias)
        return _out_proj(o, self.dim, self.dtype)
