"""Blockwise (FlashAttention-2) multi-head attention in pure JAX, for any backend.

``softmax(q k^T * hd^-0.5 + bias, where mask) v`` without ever holding the ``[Lq, Lk]``
logits: queries go in blocks of ``block_q``, keys in blocks of ``block_k``; each query
block keeps a running row maximum ``m``, row sum ``l`` and un-normalised output ``acc``
(online softmax, Dao 2023 Alg. 1) while it scans over the key blocks. The forward saves
only the output and the row statistics ``(m, l)`` (FlashAttention keeps their log-sum-exp
``m + log l``; the pair also stays exact for an all-masked row); the backward
(:func:`jax.custom_vjp`, Alg. 2) recomputes every block's probabilities from them.
Both passes are ``lax.scan`` loops, so the compiled program does not grow with L, and
the largest temporary is one block's ``[B, nh, block_q, block_k]`` logits.

Inside, q, k and v are head-major, ``[B, nh, L, hd]`` (one transpose each way at the entry):
every block product is then a plain batched matmul over ``(B, nh)``, with no per-block
transposes. The backward computes each block keys-first (``[B, nh, block_k, block_q]``) so
that three of its four products contract their left operand's minor axis, the form
XLA:CPU's fast matmul runs. On CPU, the small model's decoder attention (``[16, 3072, 8,
16]``, 512 x 512 blocks) runs faster forward and backward this way than with token-major
blocks (docs/speed-cpu.md, "The decoder's attention").

Memory (fwd + bwd) is linear in L: q, k, v, the output, ``(m, l)`` and the gradients, plus
one logits block per loop step. An optional ``bias`` / ``mask`` of ``[Lq, Lk]`` size is a
hook for short sequences (the caller's own array is already quadratic).

Numerics match :func:`jax.nn.dot_product_attention`: logits, softmax statistics and the
accumulators are in ``promote(dtype, float32)``, the output in ``q``'s dtype; a masked
logit becomes ``-0.7 * finfo.max`` (so a query whose keys are all masked gets the mean
of ``v``, as the library does) and receives no gradient. Keys added to pad L up to a
multiple of ``block_k`` are removed with ``-inf`` (they never enter a softmax).
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
from jax import lax

from llrmpp_jax.array_typing import Array, ArrayLike, Bool, Float
from llrmpp_jax.nn.variance import common_variance, full_like_varying


def _acc_dtype(dtype) -> jnp.dtype:
    """Accumulation dtype: float32, or the input's own if wider (float64)."""
    return jnp.dtype(dtype) if jnp.finfo(dtype).bits > 32 else jnp.dtype(jnp.float32)


def _pad_to(x: ArrayLike, axis: int, multiple: int) -> ArrayLike:
    extra = -x.shape[axis] % multiple
    if extra == 0 or x.shape[axis] == 1:  # size-1 axes broadcast and are never padded
        return x
    widths = [(0, 0)] * x.ndim
    widths[axis] = (0, extra)
    return jnp.pad(x, widths)


def _to_blocks(x: Array, block: int) -> Array:
    """``[B, nh, L, ...]`` (L a multiple of ``block``) -> ``[L/block, B, nh, block, ...]``."""
    b, nh, length = x.shape[:3]
    return jnp.moveaxis(x.reshape(b, nh, length // block, block, *x.shape[3:]), 2, 0)


def _from_blocks(x: Array) -> Array:
    """Inverse of :func:`_to_blocks`."""
    x = jnp.moveaxis(x, 0, 2)
    return x.reshape(*x.shape[:2], x.shape[2] * x.shape[3], *x.shape[4:])


def _slice_qk(a: ArrayLike, i: Array, bq: int, j: Array, bk: int) -> Array:
    """Block ``(i, j)`` of a ``[B|1, nh|1, Lq|1, Lk]`` bias/mask (a size-1 query axis stays size 1)."""
    qsize = 1 if a.shape[2] == 1 else bq
    qstart = 0 if a.shape[2] == 1 else i * bq
    return lax.dynamic_slice(a, (0, 0, qstart, j * bk), (a.shape[0], a.shape[1], qsize, bk))


def _block_logits(q_i, k_j, i, j, bias, mask, bq, bk, lk, scale, acc, keys_first: bool = False):
    """Scaled, biased, masked logits ``[B, nh, bq, bk]`` of query block i vs key block j
    (``keys_first``: their transpose ``[B, nh, bk, bq]``), and the where-kept mask in the
    same orientation (None without a user mask)."""
    spec = "bhkd,bhqd->bhkq" if keys_first else "bhqd,bhkd->bhqk"
    s = jnp.einsum(spec, *((k_j, q_i) if keys_first else (q_i, k_j)), preferred_element_type=acc) * scale
    orient = (lambda a: a.swapaxes(-1, -2)) if keys_first else (lambda a: a)  # noqa: E731
    if bias is not None:
        s = s + orient(_slice_qk(bias, i, bq, j, bk).astype(acc))
    keep = None
    if mask is not None:
        keep = orient(_slice_qk(mask, i, bq, j, bk))
        s = jnp.where(keep, s, jnp.asarray(-0.7 * jnp.finfo(acc).max, acc))
    if lk % bk:  # padded keys of the last block: out of every softmax
        real = (j * bk + jnp.arange(bk)) < lk
        s = jnp.where(real.reshape((1, 1, bk, 1) if keys_first else (1, 1, 1, bk)), s, jnp.asarray(-jnp.inf, acc))
    return s, keep


def _forward(q, k, v, bias, mask, bq, bk, lk):
    """Padded head-major inputs ``[B, nh, L, hd]`` -> (output ``[B, nh, Lq_pad, hd]``,
    softmax stats ``(m, l)``): row maximum and row sum of ``exp(s - m)``, each ``[Lq_pad/bq, B, nh, bq]``."""
    acc = _acc_dtype(q.dtype)
    scale = jnp.asarray(q.shape[-1] ** -0.5, acc)
    qb, kb, vb = _to_blocks(q, bq), _to_blocks(k, bk), _to_blocks(v, bk)
    b, nh, hd = q.shape[0], q.shape[1], q.shape[3]

    def q_block(_, xs):
        q_i, i = xs

        def k_block(carry, ys):
            m, l, o = carry  # noqa: E741  the docstring's row sum l
            k_j, v_j, j = ys
            s, _ = _block_logits(q_i, k_j, i, j, bias, mask, bq, bk, lk, scale, acc)
            m_new = jnp.maximum(m, s.max(axis=-1))
            alpha = jnp.exp(m - m_new)
            p = jnp.exp(s - m_new[..., None])
            l = alpha * l + p.sum(axis=-1)  # noqa: E741
            pv = jnp.einsum("bhqk,bhkd->bhqd", p.astype(v.dtype), v_j, preferred_element_type=acc)
            o = alpha[..., None] * o + pv
            return (m_new, l, o), None

        init = (
            full_like_varying(q_i, (b, nh, bq), -jnp.inf, acc),
            full_like_varying(q_i, (b, nh, bq), 0.0, acc),
            full_like_varying(q_i, (b, nh, bq, hd), 0.0, acc),
        )
        (m, l, o), _ = lax.scan(k_block, init, (kb, vb, jnp.arange(kb.shape[0])))  # noqa: E741
        o = o / l[..., None]
        # (m, l) rather than lse = m + log(l): for an all-masked row m = -0.7 * max and
        # m + log(l) would round back to m, losing the 1/l of the uniform softmax.
        return None, (o.astype(q.dtype), (m, l))

    _, (ob, stats) = lax.scan(q_block, None, (qb, jnp.arange(qb.shape[0])))
    return _from_blocks(ob), stats


def _backward(q, k, v, bias, mask, o, stats, do, bq, bk, lk):
    """Padded head-major inputs, output, softmax stats and output cotangent -> (dq, dk, dv, dbias)."""
    acc = _acc_dtype(q.dtype)
    scale = jnp.asarray(q.shape[-1] ** -0.5, acc)
    # D_i = rowsum(dO * O): the softmax Jacobian's diagonal correction, one per query.
    delta = jnp.einsum("bhqd,bhqd->bhq", do.astype(acc), o.astype(acc))
    qb, dob, delta_b = _to_blocks(q, bq), _to_blocks(do, bq), _to_blocks(delta, bq)
    kb, vb = _to_blocks(k, bk), _to_blocks(v, bk)
    nq = qb.shape[0]

    def k_block(carry, ys):
        dq, dbias = carry
        k_j, v_j, j = ys

        def q_block(inner, xs):
            dk_j, dv_j, dq, dbias = inner
            q_i, do_i, (m_i, l_i), delta_i, i = xs
            # Keys first, [B, nh, bk, bq]: three of the four products then contract the minor
            # axis of their left operand, the form XLA:CPU's fast matmul takes (a dot that
            # contracts another axis runs several times slower); ds is transposed once for dq.
            s_t, keep_t = _block_logits(q_i, k_j, i, j, bias, mask, bq, bk, lk, scale, acc, keys_first=True)
            p_t = jnp.exp(s_t - m_i[..., None, :]) / l_i[..., None, :]
            dv_j = dv_j + jnp.einsum("bhkq,bhqd->bhkd", p_t.astype(do.dtype), do_i, preferred_element_type=acc)
            dp_t = jnp.einsum("bhkd,bhqd->bhkq", v_j, do_i, preferred_element_type=acc)
            ds_t = p_t * (dp_t - delta_i[..., None, :])
            if keep_t is not None:
                ds_t = jnp.where(keep_t, ds_t, jnp.zeros((), acc))
            dk_j = dk_j + jnp.einsum("bhkq,bhqd->bhkd", ds_t.astype(q.dtype), q_i, preferred_element_type=acc) * scale
            # The barrier keeps the transpose a copy: folded into the dot it is the slow form.
            ds = lax.optimization_barrier(ds_t.swapaxes(-1, -2))
            dq_i = jnp.einsum("bhqk,bhkd->bhqd", ds.astype(q.dtype), k_j, preferred_element_type=acc) * scale
            dq = lax.dynamic_update_slice_in_dim(
                dq, lax.dynamic_slice_in_dim(dq, i * bq, bq, axis=2) + dq_i, i * bq, axis=2
            )
            if dbias is not None:
                # Sum over the axes the bias broadcasts along (batch, head, query).
                axes = tuple(ax for ax in range(3) if dbias.shape[ax] == 1)
                db = ds.sum(axis=axes, keepdims=True)
                qstart = 0 if dbias.shape[2] == 1 else i * bq
                start = (0, 0, qstart, j * bk)
                dbias = lax.dynamic_update_slice(dbias, lax.dynamic_slice(dbias, start, db.shape) + db, start)
            return (dk_j, dv_j, dq, dbias), None

        zeros = full_like_varying(do, k_j.shape, 0.0, acc)
        (dk_j, dv_j, dq, dbias), _ = lax.scan(
            q_block, (zeros, zeros, dq, dbias), (qb, dob, stats, delta_b, jnp.arange(nq))
        )
        return (dq, dbias), (dk_j, dv_j)

    dbias0 = None if bias is None else full_like_varying(do, bias.shape, 0.0, acc)
    (dq, dbias), (dkb, dvb) = lax.scan(
        k_block, (full_like_varying(do, q.shape, 0.0, acc), dbias0), (kb, vb, jnp.arange(kb.shape[0]))
    )
    dk, dv = _from_blocks(dkb), _from_blocks(dvb)
    if dbias is not None:
        dbias = dbias.astype(bias.dtype)  # pyright: ignore[reportOptionalMemberAccess] -- dbias exists only with a bias
    return dq.astype(q.dtype), dk.astype(k.dtype), dv.astype(v.dtype), dbias


def check_qkv(who: str, q: ArrayLike, k: ArrayLike, v: ArrayLike) -> None:
    """ValueError naming ``who`` unless q is ``[B, Lq, nh, hd]``, k = v ``[B, Lk, nh, hd]``, one dtype."""
    if q.ndim != 4 or k.ndim != 4 or v.shape != k.shape or q.shape[0] != k.shape[0] or q.shape[2:] != k.shape[2:]:
        raise ValueError(
            f"{who}: expected q [B, Lq, nh, hd] and k = v [B, Lk, nh, hd], got q {q.shape}, k {k.shape}, v {v.shape}"
        )
    if not q.dtype == k.dtype == v.dtype:
        raise ValueError(f"{who}: q, k, v dtypes differ: {q.dtype}, {k.dtype}, {v.dtype}")


@functools.partial(jax.custom_vjp, nondiff_argnums=(5, 6, 7))
def _attention(q, k, v, bias, mask, bq, bk, lk):
    return _forward(q, k, v, bias, mask, bq, bk, lk)[0]


def _attention_fwd(q, k, v, bias, mask, bq, bk, lk):
    o, stats = _forward(q, k, v, bias, mask, bq, bk, lk)
    return o, (q, k, v, bias, mask, o, stats)


def _attention_bwd(bq, bk, lk, res, do):
    q, k, v, bias, mask, o, stats = res
    dq, dk, dv, dbias = _backward(q, k, v, bias, mask, o, stats, do, bq, bk, lk)
    return dq, dk, dv, dbias, None


_attention.defvjp(_attention_fwd, _attention_bwd)


def blockwise_attention(
    q: Float[ArrayLike, "B Lq nh hd"],
    k: Float[ArrayLike, "B Lk nh hd"],
    v: Float[ArrayLike, "B Lk nh hd"],
    *,
    bias: Float[ArrayLike, "#B #nh #Lq Lk"] | None = None,
    mask: Bool[ArrayLike, "#B #nh #Lq Lk"] | None = None,
    block_q: int = 512,
    block_k: int = 512,
) -> Float[Array, "B Lq nh hd"]:
    """``softmax(q k^T * hd^-0.5 + bias, where mask) v`` in query x key blocks.

    ``q``: ``[B, Lq, nh, hd]``; ``k``, ``v``: ``[B, Lk, nh, hd]``; ``bias`` / ``mask``
    ``[B, nh, Lq, Lk]``, each of the first three axes possibly 1 (broadcast; ``mask`` True
    where a key takes part). Block sizes need not divide L (the last block
    is padded; a block larger than L shrinks to L). Differentiable in q, k, v and bias
    with a memory-linear backward (see the module docstring).
    """
    if block_q < 1 or block_k < 1:
        raise ValueError(f"blockwise_attention: block sizes must be >= 1, got block_q={block_q}, block_k={block_k}")
    check_qkv("blockwise_attention", q, k, v)
    b, lq, nh, _ = q.shape
    lk = k.shape[1]
    for name, a in (("bias", bias), ("mask", mask)):
        if a is not None and (
            a.ndim != 4
            or a.shape[0] not in (1, b)
            or a.shape[1] not in (1, nh)
            or a.shape[2] not in (1, lq)
            or a.shape[3] != lk
        ):
            raise ValueError(
                f"blockwise_attention: {name} has shape {a.shape}, expected [B|1, nh|1, Lq|1, Lk] = {(b, nh, lq, lk)}"
            )
    bq, bk = min(block_q, lq), min(block_k, lk)
    qp = _pad_to(q, 1, bq)
    kp, vp = _pad_to(k, 1, bk), _pad_to(v, 1, bk)
    biasp = None if bias is None else _pad_to(_pad_to(bias, 2, bq), 3, bk)
    maskp = None if mask is None else _pad_to(_pad_to(mask, 2, bq), 3, bk)
    qp, kp, vp, biasp = common_variance(qp, kp, vp, biasp)
    heads_first = lambda x: x.transpose(0, 2, 1, 3)  # noqa: E731  [B, L, nh, hd] <-> [B, nh, L, hd]
    out = _attention(heads_first(qp), heads_first(kp), heads_first(vp), biasp, maskp, bq, bk, lk)
    return heads_first(out)[:, :lq]
