"""Global multi-head attention (all tokens), and the q/k/v projections every attention shares.

The pure function :func:`multi_head_attention` does the maths; the Flax module
:class:`Attention` only owns parameters and calls it (local k-NN attention lives in
``local_attention.py`` and reuses the projections). Parameter names mirror
Long-LRM's PyTorch ``SelfAttention`` (``qkv``, ``proj``) so checkpoints convert by
transposing Linear weights; QK-norm follows LVSM (facts §6.1): RMSNorm over the head
dimension (learnable scale ``[hd]``, eps 1e-5) on q and k after the head split.
"""

from __future__ import annotations

import math
import typing

import flax.linen as nn
import jax
import jax.numpy as jnp

from llrmpp_jax.array_typing import Array, ArrayLike, Bool, DTypeLike, Float
from llrmpp_jax.config import AttentionImpl
from llrmpp_jax.nn.blockwise_attention import blockwise_attention
from llrmpp_jax.nn.initializers import DENSE_INIT
from llrmpp_jax.nn.norms import RMSNorm
from llrmpp_jax.nn.splash_attention import splash_attention

# Global-attention kernels of multi_head_attention (TransformerConfig.attention_impl).
ATTENTION_IMPLEMENTATIONS: tuple[str, ...] = typing.get_args(AttentionImpl)


def multi_head_attention(
    q: Float[ArrayLike, "*batch Lq nh hd"],
    k: Float[ArrayLike, "*batch Lk nh hd"],
    v: Float[ArrayLike, "*batch Lk nh hd"],
    *,
    bias: Float[ArrayLike, "*#batch #nh #Lq Lk"] | None = None,
    mask: Bool[ArrayLike, "*#batch #nh #Lq Lk"] | None = None,
    implementation: AttentionImpl = "blockwise",
    block_q: int = 512,
    block_k: int = 512,
) -> Float[Array, "*batch Lq nh hd"]:
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
    * ``"cudnn"`` -- the library's cuDNN flash kernel (NVIDIA GPU). The kernel takes only
      bf16/fp16/fp8: wider inputs (float32 q and k after the float32 QK-norm, as in a bf16
      training step) are cast to bfloat16 for the kernel and its output back to q's dtype.
    * ``"splash"`` -- :func:`~llrmpp_jax.nn.splash_attention.splash_attention`, the Pallas
      TPU splash-attention kernel (TPU; elsewhere only in Pallas's TPU interpret mode); blocks
      of ``block_q`` x ``block_k`` rounded up to multiples of 128; no ``bias`` or ``mask``
      (the model's global attention has neither).

    Precision: logits and softmax in ``promote(dtype, float32)`` (blockwise) or softmax
    always in float32 (library), so float64 inputs are accurate to ~1e-7 with the latter.
    """
    if implementation not in ATTENTION_IMPLEMENTATIONS:
        raise ValueError(
            f"multi_head_attention: implementation must be one of {ATTENTION_IMPLEMENTATIONS}, got {implementation!r}"
        )
    if q.ndim < 3 or k.ndim != q.ndim or v.shape != k.shape:
        raise ValueError(
            f"multi_head_attention: q, k, v must be [..., L, nh, hd] with equal ranks and "
            f"k.shape == v.shape, got q {q.shape}, k {k.shape}, v {v.shape}"
        )
    if q.shape[:-3] != k.shape[:-3] or q.shape[-2:] != k.shape[-2:]:
        raise ValueError(f"multi_head_attention: q {q.shape} and k {k.shape} must share batch dims, nh and hd")
    batch = q.shape[:-3]
    nb = math.prod(batch)
    lq, nh, hd = q.shape[-3:]
    lk = k.shape[-3]

    def to_4d(a: ArrayLike | None, name: str) -> ArrayLike | None:
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
    elif implementation == "splash":
        if bias4 is not None or mask4 is not None:
            raise ValueError("multi_head_attention: implementation='splash' takes no bias or mask")
        out = splash_attention(q4, k4, v4, block_q=block_q, block_k=block_k)
    else:
        if implementation == "cudnn" and jnp.dtype(q.dtype).itemsize > 2:  # the kernel's 16-bit inputs
            q4, k4, v4, bias4 = (None if a is None else a.astype(jnp.bfloat16) for a in (q4, k4, v4, bias4))
        # The library promotes logits to >= float32 internally, which strict dtype promotion
        # (our test configuration) rejects for float64/bfloat16 inputs; that promotion is the
        # intended behaviour, so allow it for this call only.
        with jax.numpy_dtype_promotion("standard"):
            out = jax.nn.dot_product_attention(  # pyright: ignore[reportCallIssue] -- q4, k4, v4 are arrays; bias4 and mask4 may be None, which the call takes
                q4,  # pyright: ignore[reportArgumentType] -- as above
                k4,  # pyright: ignore[reportArgumentType] -- as above
                v4,  # pyright: ignore[reportArgumentType] -- as above
                bias=bias4,
                mask=mask4,
                implementation=implementation,
            ).astype(q.dtype)
    return out.reshape(*batch, lq, nh, hd)


def _num_heads(dim: int, head_dim: int, who: str) -> int:
    if dim % head_dim:
        raise ValueError(f"{who}: dim={dim} is not a multiple of head_dim={head_dim}")
    return dim // head_dim


def _check_width(x: ArrayLike, dim: int, who: str) -> None:
    if x.ndim < 2 or x.shape[-1] != dim:
        raise ValueError(f"{who}: x must be [..., L, dim={dim}], got shape {x.shape}")


def _qkv_heads(
    x: Float[ArrayLike, "... L D"], dim: int, head_dim: int, qk_norm: bool, eps: float, dtype: DTypeLike | None
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


def _out_proj(o: Float[Array, "... L nh hd"], dim: int, dtype: DTypeLike | None) -> Float[Array, "... L D"]:
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
    implementation: AttentionImpl = "blockwise"
    dtype: DTypeLike | None = None
    block_sizes: tuple[int, int] = (512, 512)

    @nn.compact
    def __call__(self, x: Float[ArrayLike, "... L D"]) -> Float[Array, "... L D"]:
        _num_heads(self.dim, self.head_dim, "Attention")
        _check_width(x, self.dim, "Attention")
        q, k, v = _qkv_heads(x, self.dim, self.head_dim, self.qk_norm, self.norm_eps, self.dtype)
        o = multi_head_attention(
            q,
            k,
            v,
            implementation=self.implementation,
            block_q=self.block_sizes[0],
            block_k=self.block_sizes[1],
        )
        return _out_proj(o, self.dim, self.dtype)
