"""Multi-head attention: global (all tokens) and local (k nearest tokens of a 2D grid).

Pure functions do the maths; the Flax modules :class:`Attention` and
:class:`LocalAttention` only own parameters and call them. Parameter names mirror
Long-LRM's PyTorch ``SelfAttention`` (``qkv``, ``proj``) so checkpoints convert by
transposing Linear weights; QK-norm follows LVSM (facts §6.1): RMSNorm over the head
dimension (learnable scale ``[hd]``, eps 1e-5) on q and k after the head split.

Local attention (Long-LRM++ decoder, paper §3.3): every token of an ``h x w`` grid
attends to the tokens at a *fixed* set of ``k`` grid offsets, the ``k`` offsets nearest
to ``(0, 0)`` in Euclidean distance. Sharing one offset set makes the layer translation
invariant and lets the relative-position bias be computed once per layer (``[k, nh]``)
instead of per token.

Border rule: an offset that leaves the grid is *masked* (its logit is removed from the
softmax), never replaced by another in-grid token; border tokens therefore attend to
fewer than ``k`` tokens. The self offset is always in the grid, so no row is empty.
"""

from __future__ import annotations

import functools
import math

import flax.linen as nn
import jax
import jax.numpy as jnp
import numpy as np

from llrmpp_jax.array_typing import Array, Bool, Float, Int
from llrmpp_jax.nn.blockwise_attention import blockwise_attention
from llrmpp_jax.nn.norms import RMSNorm

# Global-attention kernels of multi_head_attention (TransformerConfig.attention_impl).
ATTENTION_IMPLEMENTATIONS = ("xla", "cudnn", "blockwise")

# Long-LRM ``_init_weights``: Linear weights ~ N(0, 0.02).
DENSE_INIT = nn.initializers.normal(stddev=0.02)


def multi_head_attention(
    q: Float[Array, "... Lq nh hd"],
    k: Float[Array, "... Lk nh hd"],
    v: Float[Array, "... Lk nh hd"],
    *,
    bias: Float[Array, "... nh Lq Lk"] | None = None,
    mask: Bool[Array, "... nh Lq Lk"] | None = None,
    implementation: str = "blockwise",
    block_q: int = 512,
    block_k: int = 512,
) -> Float[Array, "... Lq nh hd"]:
    """``softmax(q k^T * hd^-0.5 + bias, where mask) v`` for every head.

    ``bias`` / ``mask`` are ``[nh, Lq, Lk]`` (shared over the batch) or
    ``[..., nh, Lq, Lk]`` with the batch dims of ``q``; a size-1 head or query axis
    broadcasts. ``mask`` is True where a key takes part; a query whose keys are all
    masked gets the mean of ``v`` (library behaviour).

    ``implementation`` (one of :data:`ATTENTION_IMPLEMENTATIONS`):

    * ``"blockwise"`` -- :func:`~llrmpp_jax.nn.blockwise_attention.blockwise_attention`,
      FlashAttention-2 in pure JAX on any backend and dtype: memory linear in L, blocks
      of ``block_q`` queries x ``block_k`` keys.
    * ``"xla"`` -- ``jax.nn.dot_product_attention``'s XLA path; materialises
      ``[B, nh, Lq, Lk]`` logits (quadratic memory).
    * ``"cudnn"`` -- the library's cuDNN flash kernel (NVIDIA GPU, bf16/fp16 inputs).

    Precision: logits and softmax in ``promote(dtype, float32)`` (blockwise) or softmax
    always in float32 (library), so float64 inputs are accurate to ~1e-7 with the latter.
    """
    if implementation not in ATTENTION_IMPLEMENTATIONS:
        raise ValueError(
            f"multi_head_attention: implementation must be one of {ATTENTION_IMPLEMENTATIONS}, "
            f"got {implementation!r}"
        )
    if q.ndim < 3 or k.ndim != q.ndim or v.shape != k.shape:
        raise ValueError(
            f"multi_head_attention: q, k, v must be [..., L, nh, hd] with equal ranks and "
            f"k.shape == v.shape, got q {q.shape}, k {k.shape}, v {v.shape}"
        )
    if q.shape[:-3] != k.shape[:-3] or q.shape[-2:] != k.shape[-2:]:
        raise ValueError(
            f"multi_head_attention: q {q.shape} and k {k.shape} must share batch dims, nh and hd"
        )
    batch = q.shape[:-3]
    nb = math.prod(batch)
    lq, nh, hd = q.shape[-3:]
    lk = k.shape[-3]

    def to_4d(a: Array | None, name: str) -> Array | None:
        if a is None:
            return None
        tail_ok = a.ndim >= 3 and a.shape[-1] == lk and a.shape[-2] in (1, lq) and a.shape[-3] in (1, nh)
        if not tail_ok or a.shape[:-3] not in ((), batch):
            raise ValueError(
                f"multi_head_attention: {name} has shape {a.shape}, expected "
                f"[nh, Lq, Lk] = {(nh, lq, lk)} or {(*batch, nh, lq, lk)} (size-1 nh / Lq allowed)"
            )
        return a[None] if a.ndim == 3 else a.reshape(nb, *a.shape[-3:])

    q4, k4, v4 = q.reshape(nb, lq, nh, hd), k.reshape(nb, lk, nh, hd), v.reshape(nb, lk, nh, hd)
    bias4, mask4 = to_4d(bias, "bias"), to_4d(mask, "mask")
    if implementation == "blockwise":
        out = blockwise_attention(q4, k4, v4, bias=bias4, mask=mask4, block_q=block_q, block_k=block_k)
    else:
        # The library promotes logits to >= float32 internally, which strict dtype promotion
        # (our test configuration) rejects for float64/bfloat16 inputs; that promotion is the
        # intended behaviour, so allow it for this call only.
        with jax.numpy_dtype_promotion("standard"):
            out = jax.nn.dot_product_attention(
                q4, k4, v4, bias=bias4, mask=mask4, implementation=implementation
            )
    return out.reshape(*batch, lq, nh, hd)


@functools.lru_cache(maxsize=64)
def neighbour_table(
    h: int, w: int, k: int
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Static k-nearest-offset table of an ``h x w`` token grid (NumPy, built at trace time).

    The offsets are the ``k`` integer ``(dy, dx)`` nearest to ``(0, 0)``, ordered by
    squared distance, ties broken by ``dy`` then ``dx`` (both ascending); the same set
    is used for every token (translation invariance), so ``offsets[0] == (0, 0)``.

    Returns:
      index: ``[h*w, k]`` int32, row-major token index of token ``t``'s neighbour ``j``;
        where the neighbour leaves the grid it points at ``t`` itself (a harmless, in-range
        gather target that ``valid`` masks out).
      valid: ``[h*w, k]`` bool, True where the neighbour lies inside the grid.
      offsets: ``[k, 2]`` int32, ``(dy, dx)`` in token-grid units.
    The arrays are cached and read-only.
    """
    if h < 1 or w < 1 or k < 1:
        raise ValueError(f"neighbour_table: h, w, k must be >= 1, got h={h}, w={w}, k={k}")
    # The k offsets (0, 0..k-1) lie within distance k-1, so the k nearest lie in this square.
    r = np.arange(-(k - 1), k)
    dy, dx = (a.ravel() for a in np.meshgrid(r, r, indexing="ij"))
    order = np.lexsort((dx, dy, dy * dy + dx * dx))[:k]
    offsets = np.stack([dy[order], dx[order]], axis=-1).astype(np.int32)

    ty, tx = np.divmod(np.arange(h * w), w)
    ny = ty[:, None] + offsets[None, :, 0]
    nx = tx[:, None] + offsets[None, :, 1]
    valid = (ny >= 0) & (ny < h) & (nx >= 0) & (nx < w)
    index = np.where(valid, ny * w + nx, np.arange(h * w)[:, None]).astype(np.int32)
    for a in (index, valid, offsets):
        a.setflags(write=False)
    return index, valid, offsets


def relative_position_features(offsets: Int[np.ndarray, "k 2"]) -> Float[np.ndarray, "k 5"]:
    """Bias-MLP input per offset: ``(dx, dy, |d|, dx/|d|, dy/|d|)``, all 0 for ``(0, 0)``.

    ``offsets`` is ``[k, 2]`` ``(dy, dx)`` in token-grid units (as :func:`neighbour_table`).
    Returns ``[k, 5]`` float32 (NumPy, static).
    """
    offsets = np.asarray(offsets)
    if offsets.ndim != 2 or offsets.shape[1] != 2:
        raise ValueError(
            f"relative_position_features: offsets must be [k, 2] (dy, dx), got shape {offsets.shape}"
        )
    dy, dx = offsets[:, 0].astype(np.float64), offsets[:, 1].astype(np.float64)
    dist = np.hypot(dx, dy)
    safe = np.where(dist > 0, dist, 1.0)
    feats = np.stack([dx, dy, dist, dx / safe, dy / safe], axis=-1)
    return feats.astype(np.float32)


def local_attention(
    q: Float[Array, "... L nh hd"],
    k: Float[Array, "... L nh hd"],
    v: Float[Array, "... L nh hd"],
    index: Int[Array, "L kn"],
    valid: Bool[Array, "L kn"],
    bias: Float[Array, "kn nh"],
) -> Float[Array, "... L nh hd"]:
    """Attention of each token over its ``kn`` table neighbours, with a per-offset bias.

    ``out[l] = sum_j softmax_j(q[l].k[index[l, j]] * hd^-0.5 + bias[j]) v[index[l, j]]``
    over the ``j`` with ``valid[l, j]``. ``index`` / ``valid`` come from
    :func:`neighbour_table`; ``bias`` is ``[kn, nh]`` (one value per offset and head).

    Memory: K and V are gathered to ``[..., L, kn, nh, hd]`` each, i.e. ``2*kn`` times
    the size of k (e.g. 8160 tokens, kn=64, nh*hd=256, float32: 2 x 535 MB per image,
    kept for the backward pass unless rematerialised) -- never an ``L x L`` matrix.
    Logits and softmax run in ``promote(dtype, float32)`` (bf16 inputs: float32;
    float64 inputs: float64), the output is in ``v``'s dtype.
    """
    if q.ndim < 3 or q.shape != k.shape or k.shape != v.shape:
        raise ValueError(
            f"local_attention: q, k, v must all be [..., L, nh, hd] of one shape, got "
            f"q {q.shape}, k {k.shape}, v {v.shape}"
        )
    length, nh, hd = q.shape[-3:]
    if index.ndim != 2 or index.shape[0] != length or valid.shape != index.shape:
        raise ValueError(
            f"local_attention: index {index.shape} and valid {valid.shape} must both be "
            f"[L, kn] with L={length}"
        )
    kn = index.shape[1]
    if bias.shape != (kn, nh):
        raise ValueError(f"local_attention: bias has shape {bias.shape}, expected [kn, nh] = {(kn, nh)}")
    acc = q.dtype if jnp.finfo(q.dtype).bits > 32 else jnp.dtype(jnp.float32)  # >= float32
    lead = (1,) * (q.ndim - 3)
    # index is always in range (masked slots point at the token itself), so "clip" only
    # skips the out-of-bounds fill that the default mode would add.
    kg = jnp.take(k, index, axis=-3, mode="clip")  # [..., L, kn, nh, hd]
    vg = jnp.take(v, index, axis=-3, mode="clip")
    logits = jnp.einsum(
        "...lhd,...lkhd->...lhk", q, kg, preferred_element_type=acc
    ) * jnp.asarray(hd**-0.5, acc)
    logits = logits + bias.T.astype(acc).reshape(*lead, 1, nh, kn)
    keep = valid.reshape(*lead, length, 1, kn)
    logits = jnp.where(keep, logits, jnp.finfo(acc).min)
    weights = jax.nn.softmax(logits, axis=-1).astype(v.dtype)
    return jnp.einsum("...lhk,...lkhd->...lhd", weights, vg)


def _num_heads(dim: int, head_dim: int, who: str) -> int:
    if dim % head_dim:
        raise ValueError(f"{who}: dim={dim} is not a multiple of head_dim={head_dim}")
    return dim // head_dim


def _check_width(x: Array, dim: int, who: str) -> None:
    if x.ndim < 2 or x.shape[-1] != dim:
        raise ValueError(f"{who}: x must be [..., L, dim={dim}], got shape {x.shape}")


def _qkv_heads(
    x: Float[Array, "... L D"], dim: int, head_dim: int, qk_norm: bool, eps: float, dtype
) -> tuple[Array, Array, Array]:
    """``qkv`` Dense + head split (+ QK-norm); called inside a module's compact ``__call__``.

    Output columns of ``qkv`` are ``[q all heads | k | v]``, head-major inside each, as
    PyTorch's ``qkv(x).reshape(B, N, 3, nh, hd)``.
    """
    nh = dim // head_dim
    qkv = nn.Dense(3 * dim, use_bias=False, kernel_init=DENSE_INIT, dtype=dtype, name="qkv")(x)
    qkv = qkv.reshape(*x.shape[:-1], 3, nh, head_dim)
    q, k, v = qkv[..., 0, :, :], qkv[..., 1, :, :], qkv[..., 2, :, :]
    if qk_norm:
        q = RMSNorm(eps, name="q_norm")(q)
        k = RMSNorm(eps, name="k_norm")(k)
    return q, k, v


def _out_proj(o: Float[Array, "... L nh hd"], dim: int, dtype) -> Float[Array, "... L D"]:
    o = o.reshape(*o.shape[:-2], dim)  # heads concatenated head-major, as PyTorch
    return nn.Dense(dim, use_bias=False, kernel_init=DENSE_INIT, dtype=dtype, name="proj")(o)


class Attention(nn.Module):
    """Global multi-head self-attention over all L tokens: ``[..., L, D] -> [..., L, D]``.

    Params: ``qkv/kernel [D, 3D]``, ``proj/kernel [D, D]`` and, with ``qk_norm``,
    ``q_norm/scale [hd]``, ``k_norm/scale [hd]``. ``dtype`` is the compute dtype of the
    projections (None: from input and params); ``implementation`` and the block sizes
    ``(block_q, block_k)`` go to :func:`multi_head_attention`.
    """

    dim: int
    head_dim: int
    qk_norm: bool
    norm_eps: float = 1e-5
    implementation: str = "blockwise"
    dtype: jnp.dtype | None = None
    block_sizes: tuple[int, int] = (512, 512)

    @nn.compact
    def __call__(self, x: Float[Array, "... L D"]) -> Float[Array, "... L D"]:
        _num_heads(self.dim, self.head_dim, "Attention")
        _check_width(x, self.dim, "Attention")
        q, k, v = _qkv_heads(x, self.dim, self.head_dim, self.qk_norm, self.norm_eps, self.dtype)
        o = multi_head_attention(
            q, k, v, implementation=self.implementation,
            block_q=self.block_sizes[0], block_k=self.block_sizes[1],
        )
        return _out_proj(o, self.dim, self.dtype)


class RelativePositionBias(nn.Module):
    """``MLP(dx, dy, |d|, dx/|d|, dy/|d|)``: 5 -> ``hidden`` -> GELU (exact) -> ``num_heads``.

    Input ``[k, 5]`` from :func:`relative_position_features`, output ``[k, nh]``.
    ``fc1`` has a bias: the self offset's features are all 0, so without it the self
    bias would be pinned to 0 through the whole MLP. ``fc2`` has none: a per-head
    constant added to every logit cancels in the softmax, so it would be a dead parameter.
    """

    num_heads: int
    hidden: int = 32
    dtype: jnp.dtype | None = None

    @nn.compact
    def __call__(self, feats: Float[Array, "k 5"]) -> Float[Array, "k nh"]:
        y = nn.Dense(self.hidden, kernel_init=DENSE_INIT, dtype=self.dtype, name="fc1")(feats)
        y = nn.gelu(y, approximate=False)
        return nn.Dense(
            self.num_heads, use_bias=False, kernel_init=DENSE_INIT, dtype=self.dtype, name="fc2"
        )(y)


class LocalAttention(nn.Module):
    """k-nearest-neighbour attention on an ``h x w`` grid: ``[..., h*w, D] -> [..., h*w, D]``.

    Tokens are row-major over ``grid = (h, w)``. Params as :class:`Attention` plus
    ``rel_bias/fc1/{kernel,bias}``, ``rel_bias/fc2/kernel``. The neighbour table and the
    bias MLP input are static (built once per trace from ``grid`` and
    ``num_neighbours``); the bias MLP runs once per call on the ``k`` shared offsets.
    See :func:`local_attention` for the memory of the K/V gather.
    """

    dim: int
    head_dim: int
    qk_norm: bool
    grid: tuple[int, int]
    num_neighbours: int = 64
    bias_hidden: int = 32
    norm_eps: float = 1e-5
    dtype: jnp.dtype | None = None

    @nn.compact
    def __call__(self, x: Float[Array, "... L D"]) -> Float[Array, "... L D"]:
        nh = _num_heads(self.dim, self.head_dim, "LocalAttention")
        _check_width(x, self.dim, "LocalAttention")
        h, w = self.grid
        if x.shape[-2] != h * w:
            raise ValueError(
                f"LocalAttention: x has shape {x.shape}, expected [..., h*w, D] with "
                f"h*w = {h}*{w} = {h * w} tokens for grid {self.grid}"
            )
        index, valid, offsets = neighbour_table(h, w, self.num_neighbours)
        bias = RelativePositionBias(nh, self.bias_hidden, self.dtype, name="rel_bias")(
            jnp.asarray(relative_position_features(offsets))
        )
        q, k, v = _qkv_heads(x, self.dim, self.head_dim, self.qk_norm, self.norm_eps, self.dtype)
        o = local_attention(q, k, v, jnp.asarray(index), jnp.asarray(valid), bias)
        return _out_proj(o, self.dim, self.dtype)
