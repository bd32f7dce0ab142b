"""Global multi-head attention through the Pallas TPU splash-attention kernel.

``softmax(q k^T * hd^-0.5) v`` by ``jax.experimental.pallas.ops.tpu.splash_attention``:
a FlashAttention kernel written for the TPU's matrix unit and VMEM (Mosaic), with its own
forward and backward kernels (a custom VJP: dq, dk, dv), memory linear in L.

What this wrapper adds to the library kernel:

* **Layout**: ours is token-major ``[B, L, nh, hd]``; the kernel takes head-major
  ``[heads, L, hd]``, so q, k, v are transposed once and the batch folds into the kernel's
  head axis (``B * nh`` independent attentions).
* **Scale**: the kernel does not scale its logits; q is multiplied by ``hd^-0.5`` (in float32,
  then back to the compute dtype; exact for a power-of-four ``hd`` such as the paper's 64).
* **Blocks**: the kernel's query and key blocks must be multiples of 128 (the vector lane
  width); a requested block is rounded up to one, and shrinks to the 128-multiple that
  covers L when L is shorter (the same block serves the forward, dq and dkv kernels).
* **Ragged L**: L is padded up to a multiple of its block. Padded keys are removed exactly
  by segment ids (real keys 0, padded keys 1, every query 0: the kernel keeps only pairs
  of equal ids), so no real query ever sees a padded key and no row is all-masked (every
  query keeps the real keys). Padded queries attend the real keys and are cut from the
  output; their zero cotangent gives padded q, k, v no gradient. Without padding no
  segment ids are passed.
* **Dtypes**: the kernel computes bfloat16 or float32 inputs (float32 softmax and
  accumulators either way); other dtypes (float64, float16) are computed in float32 and
  the output returned in q's dtype. TPUs have no float64.

On a TPU the kernel compiles through Mosaic; anywhere else it runs only in Pallas's TPU
interpret mode (``jax.experimental.pallas.tpu.force_tpu_interpret_mode()`` around the trace),
which is how the CPU tests check it. XLA's cost analysis counts the kernel by the
``pl.CostEstimate`` the library attaches to it, not by its body.
"""

from __future__ import annotations

import contextlib

import jax
import jax.numpy as jnp
import numpy as np
from jax import lax
from jax._src import config as jax_config
from jax.experimental.pallas.ops.tpu import splash_attention as splash
from jax.experimental.pallas.ops.tpu.splash_attention.splash_attention_kernel import SplashAttentionKernel

from llrmpp_jax.array_typing import Array, ArrayLike, Float
from llrmpp_jax.nn.blockwise_attention import check_qkv
from llrmpp_jax.nn.variance import common_variance

LANES = 128  # the TPU vector lane width: splash's block sizes are multiples of it


def kernel_block(block: int, length: int) -> int:
    """The kernel block for a requested ``block`` over ``length`` tokens: ``block`` rounded up
    to a multiple of 128, at most the 128-multiple that covers ``length``."""
    if block < 1 or length < 1:
        raise ValueError(f"splash_attention: block and length must be >= 1, got block={block}, length={length}")
    up = lambda n: -(-n // LANES) * LANES  # noqa: E731
    return min(up(block), up(length))


def _compute_dtype(dtype) -> jnp.dtype:
    """bfloat16 and float32 go to the kernel as they are; anything else as float32."""
    d = jnp.dtype(dtype)
    return d if d in (jnp.dtype(jnp.bfloat16), jnp.dtype(jnp.float32)) else jnp.dtype(jnp.float32)


def _pad_tokens(x: Array, length: int) -> Array:
    """``[B, nh, L, hd]`` zero-padded along L to ``length``."""
    return x if x.shape[2] == length else jnp.pad(x, ((0, 0), (0, 0), (0, length - x.shape[2]), (0, 0)))


def splash_attention(
    q: Float[ArrayLike, "B Lq nh hd"],
    k: Float[ArrayLike, "B Lk nh hd"],
    v: Float[ArrayLike, "B Lk nh hd"],
    *,
    block_q: int = 512,
    block_k: int = 512,
) -> Float[Array, "B Lq nh hd"]:
    """``softmax(q k^T * hd^-0.5) v`` per batch element and head, by the splash kernel.

    ``q``: ``[B, Lq, nh, hd]``; ``k``, ``v``: ``[B, Lk, nh, hd]``, one dtype. Any Lq, Lk >= 1
    (padded to the kernel's blocks and masked exactly: module docstring). ``block_q`` /
    ``block_k``: queries / keys per kernel block (rounded to :func:`kernel_block`).
    Differentiable in q, k, v (the kernel's own backward). Runs on TPU, or in Pallas's TPU
    interpret mode elsewhere.
    """
    check_qkv("splash_attention", q, k, v)
    b, lq, nh, hd = q.shape
    lk = k.shape[1]
    bq, bk = kernel_block(block_q, lq), kernel_block(block_k, lk)
    lq_pad, lk_pad = -(-lq // bq) * bq, -(-lk // bk) * bk
    dtype = _compute_dtype(q.dtype)
    heads_first = lambda x: jnp.asarray(x).transpose(0, 2, 1, 3)  # noqa: E731  [B, L, nh, hd] <-> [B, nh, L, hd]
    scale = jnp.asarray(hd**-0.5, jnp.float32)
    qh = _pad_tokens(heads_first((jnp.asarray(q).astype(jnp.float32) * scale).astype(dtype)), lq_pad)
    kh = _pad_tokens(heads_first(jnp.asarray(k).astype(dtype)), lk_pad)
    vh = _pad_tokens(heads_first(jnp.asarray(v).astype(dtype)), lk_pad)

    blocks = splash.BlockSizes(
        block_q=bq,
        block_kv=bk,
        block_kv_compute=bk,
        block_q_dkv=bq,
        block_kv_dkv=bk,
        block_kv_dkv_compute=bk,
        block_q_dq=bq,
        block_kv_dq=bk,
    )
    # The batch folds into the kernel's head axis (every (batch, head) pair is one independent
    # attention): no vmap over the kernel, whose batching Pallas's interpret mode lacks.
    mask = splash.MultiHeadMask([splash.FullMask((lq_pad, lk_pad))] * (b * nh))
    kernel = splash.make_splash_mha_single_device(mask, block_sizes=blocks)
    segments = None
    if lk_pad != lk:  # padded keys 1, real keys and every query 0 (pairs of equal ids attend)
        segments = splash.SegmentIds(
            q=jnp.asarray(np.zeros(lq_pad, np.int32)), kv=jnp.asarray((np.arange(lk_pad) >= lk).astype(np.int32))
        )
    fold = lambda x: x.reshape(b * nh, *x.shape[2:])  # noqa: E731  [B, nh, L, hd] -> [B nh, L, hd]
    qf, kf, vf = common_variance(fold(qh), fold(kh), fold(vh))  # one variance for all three (see _typed_kernel)
    out = _typed_kernel(kernel, segments, qf, kf, vf)  # pyright: ignore[reportArgumentType] -- common_variance returns arrays for arrays
    return heads_first(out.reshape(b, nh, lq_pad, hd)[:, :, :lq]).astype(q.dtype)


def _typed_kernel(kernel: SplashAttentionKernel, segments, q: Array, k: Array, v: Array) -> Array:
    """``kernel(q, k, v, segment_ids=segments)`` with a VJP, usable inside ``jax.shard_map``
    (the trainer's step).

    Under shard_map's varying-manual-axes typing, ``pallas_call`` needs each output's
    variance declared in its ``out_shape``, which the library's splash kernels do not
    declare. So the kernel and its VJP run with that typing switched off (as Pallas itself
    does while tracing a kernel body), and the output and cotangents get their primals'
    variance back by adding a zero that carries it (q, k, v share one variance). Nothing
    differentiates through the untyped values (this ``custom_vjp`` hides them), so no
    transpose sees a wrong type. Outside shard_map the zeros are plain zeros.
    The kernel (its block-mask arrays) and the segment ids are arguments, not closures, so
    that the residuals hold no value of an enclosing trace; they get no cotangent.
    """

    def apply(kernel, segments, q, k, v):
        return kernel(q, k, v, segment_ids=segments)

    @jax.custom_vjp
    def run(kernel, segments, q, k, v):  # without a gradient: the kernel that saves no residuals
        zero = lax.full_like(q, 0, q.dtype, ())
        with untyped():
            out = apply(kernel, segments, q * 1, k * 1, v * 1)
        return out + zero

    def untyped():
        """Typing off; for bfloat16 operands the backend's own matmul precision (Mosaic refuses a
        float32 contract precision on bf16 operands, as a global ``"highest"`` would ask;
        the MXU multiplies bf16 exactly into float32 anyway)."""
        stack = contextlib.ExitStack()
        stack.enter_context(jax_config._check_vma(False))  # the switch Pallas uses while tracing a kernel body
        if q.dtype == jnp.bfloat16:
            stack.enter_context(jax.default_matmul_precision("default"))
        return stack

    def _fwd(kernel, segments, q, k, v):
        zero = lax.full_like(q, 0, q.dtype, ())
        with untyped():
            # With the typing off every op's result is untyped (invariant): ``x * 1`` drops
            # the inputs' variance, so the kernel and its VJP see one consistent typing.
            out, vjp = jax.vjp(lambda q, k, v: apply(kernel, segments, q, k, v), q * 1, k * 1, v * 1)
        return out + zero, (vjp, zero)

    def _bwd(res, do):
        vjp, zero = res
        with untyped():
            grads = vjp(do * 1)
        return (None, None, *(g + zero.astype(g.dtype) for g in grads))

    run.defvjp(_fwd, _bwd)
    return run(kernel, segments, q, k, v)
