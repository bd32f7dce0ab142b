"""Mamba2's selective scan (SSD, "state space duality"), three ways.

All three compute, per head ``h`` (of ``nh``) and per batch element, with
``g = h // (nh / ngroups)`` the group the head reads ``B``/``C`` from::

    state_t = exp(dt_t * A_h) * state_{t-1} + dt_t * x_t B_t^T      state: [P, n], state_{-1} = 0
    y_t     = state_t C_t + D_h * x_t                               y_t:   [P]

* :func:`ssd_scan` -- the chunked SSD algorithm (Mamba-2 paper, ``ssd_minimal.py``):
  intra-chunk outputs, per-chunk states, an inter-chunk recurrence over chunk states
  (``lax.associative_scan`` by default, or ``lax.scan``) and state-to-output. Every
  chunk computation is an einsum (batched matmul). O(L * Q) work for chunk size Q. The
  ``[Q, Q]`` intra-chunk score blocks are computed a bounded group of chunks at a time and
  recomputed in the backward (:func:`_map_chunk_groups`), so the memory the scan keeps or
  holds at once is O(L * (nh * P + n)) plus one group's blocks, not O(L * nh * Q).
  ``inter_chunk="fused"`` instead runs all four steps chunk by chunk in one ``lax.scan``
  carrying the state (:func:`_ssd_fused`): the fastest form on CPU (the state stays in
  cache; docs/results.md, "Selective scan (SSD) on CPU").
* :func:`ssd_dense` -- the same chunks, but the inter-chunk step is the dense
  O(chunks^2) einsum of ``ssd_minimal_discrete``; a second oracle for the scan.
* :func:`ssd_sequential` -- the recurrence above as a ``lax.scan`` over time; the test
  oracle (slow, and its backward stores one state per time step).

Conventions shared by all three: ``dt`` is already ``softplus(dt_raw + dt_bias)``; ``A``
is the (negative) continuous-time decay ``-exp(A_log)``. Exponents are never positive
when ``dt >= 0`` and ``A <= 0``, so no ``exp`` can overflow. Accumulation is float32
(float64 for float64 inputs); matmul operands keep the input dtype (so bf16 inputs run
bf16 matmuls with float32 accumulation). The output has the dtype of ``x``.
"""

from __future__ import annotations

import functools
import math
from typing import Literal, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from llrmpp_jax.array_typing import Array, ArrayLike, Float
from llrmpp_jax.nn.variance import common_variance, full_like_varying

InterChunk = Literal["associative", "sequential", "dense", "fused"]


def _acc_dtype(dtype: jnp.dtype) -> jnp.dtype:
    """Accumulation dtype: float64 for float64 inputs (oracles), float32 otherwise."""
    return jnp.dtype(jnp.float64) if dtype == jnp.float64 else jnp.dtype(jnp.float32)


def _check_inputs(x, dt, A, B, C, D, chunk_size: int | None = None) -> None:
    """Raise ``ValueError`` naming the offending argument and the expected shape."""
    if chunk_size is not None and (not isinstance(chunk_size, int) or chunk_size < 1):
        raise ValueError(f"ssd: chunk_size must be a positive int, got {chunk_size!r}")
    if x.ndim < 3:
        raise ValueError(f"ssd: x must be [..., L, nh, P], got shape {x.shape}")
    *batch, L, nh, P = x.shape
    batch = tuple(batch)
    if dt.shape != (*batch, L, nh):
        raise ValueError(f"ssd: dt has shape {dt.shape}, expected {(*batch, L, nh)} (x is {x.shape})")
    if A.shape != (nh,):
        raise ValueError(f"ssd: A has shape {A.shape}, expected {(nh,)}")
    if D is not None and D.shape != (nh,):
        raise ValueError(f"ssd: D has shape {D.shape}, expected {(nh,)}")
    if B.ndim != x.ndim or B.shape[:-2] != (*batch, L):
        raise ValueError(f"ssd: B has shape {B.shape}, expected {(*batch, L, 'g', 'n')}")
    if C.shape != B.shape:
        raise ValueError(f"ssd: C has shape {C.shape}, expected the shape of B {B.shape}")
    g = B.shape[-2]
    if g < 1 or nh % g:
        raise ValueError(f"ssd: nh={nh} heads (x {x.shape}) is not a multiple of ngroups={g} (B {B.shape})")


def segment_sum(a: Float[Array, "... t"]) -> Float[Array, "... t t"]:
    """Segment sums ``out[..., i, j] = sum_{k=j+1..i} a[..., k]`` for ``j <= i``, ``-inf`` above
    (``t`` steps: a chunk's positions, or the chunks).

    ``exp(segment_sum(dt * A))`` is the decay from step ``j`` to step ``i`` (1 on the
    diagonal, 0 above it). Built as a masked cumsum (``ssd_minimal.segsum``), not as a
    difference of running sums, so no precision is lost to cancellation on long chunks.
    """
    T = a.shape[-1]
    lead = (1,) * (a.ndim - 1)
    rep = jnp.broadcast_to(a[..., :, None], (*a.shape, T))  # rep[..., k, j] = a_k
    strictly_below = jnp.tril(jnp.ones((T, T), dtype=bool), -1).reshape(*lead, T, T)  # k > j
    sums = jnp.cumsum(jnp.where(strictly_below, rep, 0.0), axis=-2)
    on_or_below = jnp.tril(jnp.ones((T, T), dtype=bool), 0).reshape(*lead, T, T)  # i >= j
    return jnp.where(on_or_below, sums, -jnp.inf)


def _compensated_cumsum(a: Float[Array, "... t"]) -> tuple[Float[Array, "... t"], Float[Array, "... t"]]:
    """Inclusive running sum over the last axis as ``hi + lo`` (Kahan/TwoSum): ``hi`` the
    float running sum, ``lo`` its accumulated rounding error, so ``hi + lo`` is exact to
    ~eps^2 relative and differences ``(hi_i - hi_j) + (lo_i - lo_j)`` lose nothing to
    cancellation. A ``lax.scan`` over T on ``[...]``-sized slices (cheap: no T x T work)."""

    def step(carry, a_t):
        hi, lo = carry
        s = hi + a_t
        bp = s - hi
        lo = lo + ((hi - (s - bp)) + (a_t - bp))  # TwoSum: exact error of hi + a_t
        return (s, lo), (s, lo)

    zeros = jnp.zeros_like(a[..., 0])  # keeps a's device variance (nn/variance.py)
    _, (hi, lo) = jax.lax.scan(step, (zeros, zeros), jnp.moveaxis(a, -1, 0))
    return jnp.moveaxis(hi, 0, -1), jnp.moveaxis(lo, 0, -1)


def _inter_chunk_states(
    chunk_log_decay: Float[Array, "b c g hg"],
    chunk_states: Float[Array, "b c g hg P n"],
    method: InterChunk,
) -> Float[Array, "b c g hg P n"]:
    """State entering each chunk: ``S_in[0] = 0``, ``S_in[c+1] = exp(a_c) S_in[c] + s_c``.

    ``chunk_log_decay`` a_c is the sum of ``dt * A`` over chunk c; ``chunk_states`` s_c the
    state chunk c produces from zero (step 2 of SSD).
    """
    if method == "sequential":

        def step(carry, inputs):
            a, s = inputs
            return jnp.exp(a)[..., None, None] * carry + s, carry

        _, s_in = jax.lax.scan(
            step,
            jnp.zeros_like(chunk_states[:, 0]),
            (jnp.moveaxis(chunk_log_decay, 1, 0), jnp.moveaxis(chunk_states, 1, 0)),
        )
        return jnp.moveaxis(s_in, 0, 1)
    if method == "associative":
        # Elements (a, s) are affine maps S -> exp(a) S + s; composing them is associative.
        # Log-decays add, so chunk-to-chunk decays are sums of exponents, not products.
        def combine(first, second):
            a1, s1 = first
            a2, s2 = second
            return a1 + a2, jnp.exp(a2)[..., None, None] * s1 + s2

        _, s_out = jax.lax.associative_scan(combine, (chunk_log_decay, chunk_states), axis=1)
    elif method == "dense":
        # ssd_minimal's O(chunks^2) form: state after chunk z = sum_{c<=z} decay(c->z) s_c.
        decay = jnp.exp(segment_sum(jnp.moveaxis(chunk_log_decay, 1, -1)))  # [b, g, hg, z, c]
        s_out = jnp.einsum("bghzc,bcghpn->bzghpn", decay.astype(chunk_states.dtype), chunk_states)
    else:
        raise ValueError(f"ssd: inter_chunk must be 'associative', 'sequential' or 'dense', got {method!r}")
    # Exclusive: chunk c starts from the state after chunk c-1.
    return jnp.concatenate([jnp.zeros_like(s_out[:, :1]), s_out[:, :-1]], axis=1)


# Score entries ([b, chunks, nh, Q, Q], float32: 4 bytes each) per step of the intra-chunk
# loop: 16 MiB, so the loop's live [Q, Q] blocks are a few times that whatever L is, and
# each step is still a batched matmul of >= one chunk of every head.
_GROUP_SCORES = 1 << 22


def _chunk_log_decays(dA: Float[Array, "b c Q g hg"]) -> tuple[Float[Array, "b c Q g hg"], Float[Array, "b c Q g hg"]]:
    """``(from_start, to_end)``: ``sum_{k<=l} dA_k`` and ``sum_{k>l} dA_k`` within each chunk
    (axis 2). ``to_end`` is a reverse exclusive cumsum, not a difference: no cancellation.
    The two leading axes are batch and chunks in either order (the fused scan's are ``[c, b]``)."""
    rev = jnp.flip(jnp.cumsum(jnp.flip(dA, axis=2), axis=2), axis=2)  # sum_{k>=l}
    return jnp.cumsum(dA, axis=2), jnp.concatenate([rev[:, :, 1:], jnp.zeros_like(rev[:, :, :1])], axis=2)


def _intra_chunk(
    Cc: Float[Array, "b c Q g n"],
    Bc: Float[Array, "b c Q g n"],
    hi: Float[Array, "b c g hg Q"],
    lo: Float[Array, "b c g hg Q"],
    xdt_bt: Float[Array, "b c g hg Q P"],
    *,
    cd: jnp.dtype,
    acc: jnp.dtype,
) -> Float[Array, "b c g hg Q P"]:
    """Diagonal blocks: ``y_l = sum_{s<=l} (C_l . B_s) decay(s->l) dt_s x_s`` within each chunk.

    ``decay(s->l) = exp(cs_l - cs_s)`` from the chunk's running sum of ``dt * A`` carried
    as an unevaluated pair ``hi + lo`` (compensated), so the difference keeps full
    precision even where cs reaches -1e4; the scores are then one fused elementwise pass
    over the ``[hg, Q, Q]`` blocks (a masked cumsum over them costs several passes, see
    :func:`segment_sum`). ``xdt_bt`` is ``dt * x`` in the matmul dtype ``cd``. The output
    keeps the batch axes leading (``[b, c, g, hg, Q, P]``): XLA:CPU writes a batched
    matmul's result faster in that layout than transposed to ``[b, c, Q, g, hg, P]``.
    """
    Q = hi.shape[-1]
    seg = (hi[..., :, None] - hi[..., None, :]) + (lo[..., :, None] - lo[..., None, :])
    causal = jnp.tril(jnp.ones((Q, Q), dtype=bool)).reshape(1, 1, 1, 1, Q, Q)  # s <= l
    CB = jnp.einsum("bclgn,bcsgn->bcgls", Cc, Bc, preferred_element_type=acc)
    # min(seg, 0): seg > 0 only above the diagonal, where exp could overflow (and poison the
    # backward of the where with inf * 0).
    decay = jnp.exp(jnp.minimum(seg, jnp.zeros((), acc)))
    scores = jnp.where(causal, CB[:, :, :, None] * decay, jnp.zeros((), acc)).astype(cd)
    return jnp.einsum("bcghls,bcghsp->bcghlp", scores, xdt_bt, preferred_element_type=acc)


def _map_chunk_groups(fn, groups: int, *args: Array) -> Array:
    """``fn(*args)`` for arrays chunked along axis 1, computed ``groups`` chunk groups at a
    time (``lax.map``) under ``jax.checkpoint``: the backward recomputes one group's
    ``[Q, Q]`` blocks at a time instead of storing them all, so the memory this costs is
    one group's, not O(L * Q) (the remat costs one more forward of ``fn``)."""

    def split(t: Array) -> Array:
        return jnp.moveaxis(t.reshape(t.shape[0], groups, t.shape[1] // groups, *t.shape[2:]), 1, 0)

    out = jax.lax.map(jax.checkpoint(lambda a: fn(*a)), tuple(split(t) for t in args))
    out = jnp.moveaxis(out, 0, 1)
    return out.reshape(out.shape[0], -1, *out.shape[3:])


# The fused scan's two state matmuls, with hand-written VJPs. XLA:CPU's dot wants each operand
# row-major along the contraction; with autodiff's own VJPs of these einsums it transposed the
# [n, hg*P] state (1.5 MB per chunk at the paper's sizes) twice per chunk in the backward. With
# these (the products that contract over hg*P written as (S R^T)^T) it transposes it once, which
# shortens the backward (docs/lab-notes.md, "SSD scan speed on CPU: the fused form").


def _state_dot_nt(S: Float[Array, "b g n hgP"], R: Float[Array, "b Q g hgP"], acc) -> Float[Array, "b Q g n"]:
    """``sum_k R[b, l, g, k] S[b, g, n, k]``, as ``(S R^T)^T``."""
    return jnp.einsum("bgnk,blgk->bgnl", S, R, preferred_element_type=acc).transpose(0, 3, 1, 2)


@functools.partial(jax.custom_vjp, nondiff_argnums=(2,))
def _state_read(C: Float[Array, "b Q g n"], S: Float[Array, "b g n hgP"], acc) -> Float[Array, "b Q g hgP"]:
    """State -> output: ``C S`` per group."""
    return jnp.einsum("blgn,bgnk->blgk", C, S, preferred_element_type=acc)


@functools.partial(jax.custom_vjp, nondiff_argnums=(2,))
def _state_write(B: Float[Array, "b Q g n"], E: Float[Array, "b Q g hgP"], acc) -> Float[Array, "b g n hgP"]:
    """Tokens -> state: ``B^T E`` per group."""
    return jnp.einsum("blgn,blgk->bgnk", B, E, preferred_element_type=acc)


def _read_bwd(acc, res, dR):
    C, S = res
    dR = dR.astype(C.dtype)
    return _state_dot_nt(S, dR, acc).astype(C.dtype), _state_write(C, dR, acc).astype(S.dtype)  # pyright: ignore[reportAttributeAccessIssue] -- custom_vjp results are arrays


def _write_bwd(acc, res, G):
    B, E = res
    G = G.astype(B.dtype)
    return _state_dot_nt(G, E, acc).astype(B.dtype), _state_read(B, G, acc).astype(E.dtype)  # pyright: ignore[reportAttributeAccessIssue] -- custom_vjp results are arrays


_state_read.defvjp(lambda C, S, acc: (_state_read(C, S, acc), (C, S)), _read_bwd)
_state_write.defvjp(lambda B, E, acc: (_state_write(B, E, acc), (B, E)), _write_bwd)


# A chunk's diagonal block is factorised (see _ssd_fused) only where every head's decay
# across the chunk spans at most this many nats: the factors then stay within e^{+-60}, away
# from float32/bfloat16 over- and underflow (e^{+-87}). Their rounding grows with the span and
# stays within the tests' tolerances at 120 nats; 120 rather than 60 lets about half of the
# layers of a model at Long-LRM's init (dt, A per head) factorise every chunk of 128, not a
# few (docs/lab-notes.md, "SSD scan speed on CPU: the fused form").
_FACTOR_SPAN = 120.0


class _FusedMeta(NamedTuple):
    """Static sizes and dtypes of the fused scan (hashable: a ``custom_vjp`` nondiff argument)."""

    b: int
    Q: int
    g: int
    n: int
    hg: int
    P: int
    acc: jnp.dtype
    cd: jnp.dtype
    out: jnp.dtype


# One chunk's inputs, each with the chunk axis removed: x [b, Q, g, hg, P], B and C [b, Q, g, n],
# dt, hi, lo [b, Q, g, hg], the four per-token scales (s_in, s_out, s_start, s_end)
# [b, Q, g, hg], the chunk's total decay [b, g, hg] and exp(mid) [b, g, hg].
_Chunk = tuple


def _fused_step(
    meta: _FusedMeta, choose_per_chunk: bool, state: Array, chunk: _Chunk, factored: Array, skip: Array | None
) -> tuple[Array, Array]:
    """One chunk of :func:`_ssd_fused`: ``(state entering it, its inputs) -> (state leaving it, y)``.

    ``state`` is ``[b, g, n, hg, P]`` (``meta.acc``); ``y`` is ``[b, Q, g, hg, P]`` in
    ``meta.out``. With ``choose_per_chunk`` the diagonal block takes the shared form where
    ``factored`` (a scalar bool) holds and the per-head form elsewhere; without it, the
    shared form (the caller knows every chunk factorises).
    """
    b, Q, g, n, hg, P, acc, cd, _ = meta
    xq, Bq, Cq, dtq, hq, lq, (s_in, s_out, s_start, s_end), decay, e_mid = chunk
    causal = jnp.tril(jnp.ones((Q, Q), dtype=bool)).reshape(1, 1, Q, Q)  # [b, g, l, s]: s <= l
    xa = xq.astype(acc)
    CB = jnp.where(causal, jnp.einsum("blgn,bsgn->bgls", Cq, Bq, preferred_element_type=acc), 0.0)
    read = _state_read(Cq, state.reshape(b, g, n, hg * P).astype(cd), acc).reshape(b, Q, g, hg, P)  # pyright: ignore[reportAttributeAccessIssue] -- the scan carry is an array

    def shared(_):  # the diagonal block before its l-side factor exp(d_l)
        xs = (xa * s_in[..., None]).astype(cd)
        return jnp.einsum("bgls,bsghp->blghp", CB.astype(cd), xs, preferred_element_type=acc)

    def per_head(_):  # _intra_chunk's algebra in this layout (calling it is slower)
        seg = (hq[:, :, None] - hq[:, None]) + (lq[:, :, None] - lq[:, None])  # [b, l, s, g, hg]
        scores = CB.transpose(0, 2, 3, 1)[..., None] * jnp.exp(jnp.minimum(seg, 0.0))
        scores = jnp.where(causal.reshape(1, Q, Q, 1, 1), scores, 0.0).astype(cd)
        xdt = (xa * dtq[..., None]).astype(cd)
        return jnp.einsum("blsgh,bsghp->blghp", scores, xdt, preferred_element_type=acc)

    if choose_per_chunk:
        y = jax.lax.cond(factored, lambda _: shared(_) * s_out[..., None], per_head, None)
        y = y + s_start[..., None] * read
    else:
        # exp(cs_l) = exp(d_l) exp(mid): the read-out shares the diagonal block's l-side
        # factor, so one scaling of their sum, and one per-token reduction fewer in the
        # backward (exp(mid) has no gradient).
        y = (shared(None) + e_mid[:, None, :, :, None] * read) * s_out[..., None]
    if skip is not None:
        y = y + skip * xa
    xe = (xa * s_end[..., None]).astype(cd).reshape(b, Q, g, hg * P)
    state = decay[:, :, None, :, None] * state + _state_write(Bq, xe, acc).reshape(b, g, n, hg, P)  # pyright: ignore[reportAttributeAccessIssue] -- the scan carry is an array
    return state, y.astype(meta.out)


def _run_chunks(meta: _FusedMeta, factor: Array, xs: _Chunk, skip: Array | None, keep_states: bool):
    """All chunks in one ``lax.scan`` from the zero state: ``y`` ``[nc, b, Q, g, hg, P]``, and with
    ``keep_states`` also the state entering each chunk ``[nc, b, g, n, hg, P]``.

    One ``lax.cond`` for the whole sequence picks the loop: a per-chunk ``lax.cond`` inside it
    slows fwd+bwd even when every chunk takes the shared form, so the loop with the per-chunk choice runs
    only when some chunk does not factorise. Under ``vmap`` a ``lax.cond`` runs both branches: batch through the
    leading axes.
    """
    state0 = full_like_varying(xs[0], (meta.b, meta.g, meta.n, meta.hg, meta.P), 0.0, meta.acc)

    def run(choose_per_chunk: bool):
        def body(state, inputs):
            chunk, factored = inputs
            new, y = _fused_step(meta, choose_per_chunk, state, chunk, factored, skip)
            return new, ((y, state) if keep_states else y)

        return jax.lax.scan(body, state0, (xs, factor))[1]

    return jax.lax.cond(jnp.all(factor), lambda: run(False), lambda: run(True))


# The fused loop's VJP is written out: the forward keeps the state entering each chunk, the
# backward runs the chunks in reverse, recomputing each one's step from its state (the work of
# a remat'd scan). Autodiff of a `jax.checkpoint`ed step under the whole-sequence `lax.cond`
# passed the x-, B- and C-sized residuals out of the cond, copied, and fwd+bwd took longer than
# this.
@functools.partial(jax.custom_vjp, nondiff_argnums=(0,))
def _chunk_loop(meta: _FusedMeta, factor: Array, xs: _Chunk, skip: Array | None) -> Array:
    """``y`` ``[nc, b, Q, g, hg, P]`` of every chunk (:func:`_run_chunks`); ``factor`` ``[nc]`` bool."""
    return _run_chunks(meta, factor, xs, skip, keep_states=False)


def _chunk_loop_fwd(meta, factor, xs, skip):
    y, states = _run_chunks(meta, factor, xs, skip, keep_states=True)
    return y, (factor, xs, skip, states)


def _chunk_loop_bwd(meta, res, dy):
    factor, xs, skip, states = res

    def run(choose_per_chunk: bool):
        def body(carry, inputs):
            d_state, d_skip = carry
            chunk, factored, state, dy_c = inputs
            _, vjp = jax.vjp(lambda s, c, k: _fused_step(meta, choose_per_chunk, s, c, factored, k), state, chunk, skip)
            d_state, d_chunk, d_k = vjp((d_state, dy_c))
            return (d_state, jax.tree.map(jnp.add, d_skip, d_k)), d_chunk

        d0 = (full_like_varying(states, states.shape[1:], 0.0, states.dtype), jax.tree.map(jnp.zeros_like, skip))
        (_, d_skip), d_xs = jax.lax.scan(body, d0, (xs, factor, states, dy), reverse=True)
        return d_xs, d_skip

    d_xs, d_skip = jax.lax.cond(jnp.all(factor), lambda: run(False), lambda: run(True))
    return np.zeros(factor.shape, jax.dtypes.float0), d_xs, d_skip


_chunk_loop.defvjp(_chunk_loop_fwd, _chunk_loop_bwd)


def _ssd_fused(x, dt, A, B, C, chunk_size: int, D):
    """``ssd_scan(..., inter_chunk="fused")``: one ``lax.scan`` over chunks whose carry is the
    ``[b, g, n, hg, P]`` state entering the chunk, everything token-major.

    Per chunk of Q tokens, with ``cs`` the running sum of ``dt * A`` and ``d = cs - m`` about
    the chunk's middle value ``m``:

    * diagonal block ``y_l = sum_{s<=l} (C_l . B_s) exp(cs_l - cs_s) dt_s x_s``, computed as
      ``exp(d_l) * sum_s [C B^T]_{ls} (exp(-d_s) dt_s x_s)``: one ``[Q, Q] @ [Q, hg * P]``
      matmul shared by a group's heads, where the per-head form needs an ``[nh, Q, Q]``
      block of exponentials and ``nh`` thin matmuls. Exact in real arithmetic; used where
      every head's decay spans at most ``_FACTOR_SPAN`` nats across the chunk, else the
      chunk takes the per-head form (:func:`_intra_chunk`'s algebra). The choice is made
      once for the sequence where it can be: if every chunk factorises (the usual case:
      the bench's inputs span <= 58 nats per chunk of 128), a loop with no choice in it
      runs (:func:`_run_chunks`);
    * ``y_l += exp(cs_l) C_l . S`` (state -> output; in the loop with no choice written
      ``exp(d_l) exp(m) C_l . S`` and summed with the diagonal block before its factor
      ``exp(d_l)``), ``y_l += D x_l``;
    * ``S <- exp(cs_Q) S + sum_l B_l (exp(cs_Q - cs_l) dt_l x_l)^T``.

    Every ``x``-sized operand is read inside the loop in its stored ``[L, nh, P]`` layout and
    ``y`` is written in it, so nothing of that size is transposed or scaled outside the loop
    (outside it only ``[L, nh]`` decay factors are computed). The loop's VJP is written out
    (:func:`_chunk_loop`): the backward keeps one state per chunk and recomputes the rest.
    At the paper's block sizes the ops outside the loop cost far less than in the head-major
    form this replaced.
    """
    _check_inputs(x, dt, A, B, C, D, chunk_size)
    *batch, L, nh, P = x.shape
    g, n = B.shape[-2:]
    hg = nh // g
    acc, cd = _acc_dtype(x.dtype), x.dtype
    Q, b = chunk_size, math.prod(batch)
    nc = -(-L // Q)

    def chunks(t: Array, tail: tuple[int, ...]) -> Array:  # [nc, b, Q, *tail]; zero padding is causal-safe
        t = jnp.pad(t.reshape(b, L, *tail), [(0, 0), (0, nc * Q - L)] + [(0, 0)] * len(tail))
        return jnp.moveaxis(t.reshape(b, nc, Q, *tail), 1, 0)

    xc, Bc, Cc = chunks(x, (g, hg, P)), chunks(B, (g, n)).astype(cd), chunks(C, (g, n)).astype(cd)
    dtc = chunks(dt, (g, hg)).astype(acc)
    dA = dtc * A.reshape(1, 1, 1, g, hg).astype(acc)  # [nc, b, Q, g, hg], <= 0
    hi, lo = (jnp.moveaxis(t, -1, 2) for t in _compensated_cumsum(jnp.moveaxis(dA, 2, -1)))
    mid = jax.lax.stop_gradient(0.5 * (hi[:, :, :1] + hi[:, :, -1:]))  # cancels exactly: no gradient
    d = (hi - mid) + lo
    factor = jnp.max(hi[:, :, 0] - hi[:, :, -1], axis=(1, 2, 3)) <= _FACTOR_SPAN  # [nc]
    # Chunks that take the per-head form never use the factors; 0 there keeps exp(+-d) finite
    # (e^+-d overflows past ~88 nats, and inf * 0 would make the backward NaN).
    d = jnp.where(factor[:, None, None, None, None], d, jnp.zeros((), acc))
    log_from_start, to_end = _chunk_log_decays(dA)
    scales = (dtc * jnp.exp(-d), jnp.exp(d), jnp.exp(log_from_start), dtc * jnp.exp(to_end))
    chunk_decay = jnp.exp(log_from_start[:, :, -1])  # [nc, b, g, hg]
    meta = _FusedMeta(b, Q, g, n, hg, P, acc, jnp.dtype(cd), jnp.dtype(x.dtype))
    xs = (xc, Bc, Cc, dtc, hi, lo, scales, chunk_decay, jnp.exp(mid[:, :, 0]))
    skip = None if D is None else common_variance(xc, D.reshape(1, 1, g, hg, 1).astype(acc))[1]
    y = _chunk_loop(meta, factor, xs, skip)
    y = jnp.moveaxis(y, 0, 1).reshape(b, nc * Q, nh, P)[:, :L]  # pyright: ignore[reportArgumentType] -- custom_vjp results are arrays
    return y.reshape(*batch, L, nh, P)


def _ssd_chunked(x, dt, A, B, C, chunk_size: int, D, inter_chunk: InterChunk):
    _check_inputs(x, dt, A, B, C, D, chunk_size)
    *batch, L, nh, P = x.shape
    g, n = B.shape[-2:]
    hg = nh // g  # heads per group; head h reads group h // hg (mamba_ssm's repeat order)
    acc, cd = _acc_dtype(x.dtype), x.dtype
    Q = chunk_size
    b = math.prod(batch)
    # Chunks are processed in `groups` equal groups of at most _GROUP_SCORES score entries
    # ([b, chunks, nh, Q, Q]); L is padded to a whole number of groups (< groups extra chunks).
    needed = -(-L // Q)
    groups = -(-needed // max(1, _GROUP_SCORES // (b * nh * Q * Q)))
    nc = -(-needed // groups) * groups

    # Zero padding at the end is causal-safe: dt = 0 means no input and decay exp(0) = 1.
    def chunks(t: Array, tail: tuple[int, ...]) -> Array:
        t = t.reshape(b, L, *tail)
        t = jnp.pad(t, [(0, 0), (0, nc * Q - L)] + [(0, 0)] * len(tail))
        return t.reshape(b, nc, Q, *tail)

    xc = chunks(x, (g, hg, P))
    dtc = chunks(dt, (g, hg)).astype(acc)
    Bc = chunks(B, (g, n)).astype(cd)
    Cc = chunks(C, (g, n)).astype(cd)
    dA = dtc * A.reshape(g, hg).astype(acc)[None, None, None]  # [b, c, Q, g, hg], <= 0
    xdt = xc.astype(acc) * dtc[..., None]  # [b, c, Q, g, hg, P]

    hi, lo = _compensated_cumsum(jnp.moveaxis(dA, 2, -1))  # [b, c, g, hg, Q]
    # x moved to [b, c, g, hg, s, P] first: with the batch axes leading on both operands
    # XLA:CPU emits one batched matmul instead of a strided loop (much faster at paper sizes).
    xdt_bt = jnp.moveaxis(xdt.astype(cd), 2, 4)
    # Chunk states from zero use decay(l->end).
    log_decay_from_start, to_end = _chunk_log_decays(dA)  # [b, c, Q, g, hg]
    xdt_end = (xdt * jnp.exp(to_end)[..., None]).astype(cd)

    # 1. Intra-chunk (diagonal blocks), in groups of chunks (see _intra_chunk).
    y = _map_chunk_groups(lambda *a: _intra_chunk(*a, cd=cd, acc=acc), groups, Cc, Bc, hi, lo, xdt_bt)
    # 2. Chunk states from zero: s = sum_l decay(l->end) dt_l x_l B_l^T.
    states = jnp.einsum("bclgn,bclghp->bcghpn", Bc, xdt_end, preferred_element_type=acc)
    # 3. Inter-chunk recurrence over chunk states.
    s_in = _inter_chunk_states(log_decay_from_start[:, :, -1], states, inter_chunk)
    # 4. State to output: y_l += decay(start->l) C_l . S_in. Everything in the matmuls'
    #    [b, c, g, hg, Q, P] layout; one transpose back at the end.
    y_off = jnp.einsum("bclgn,bcghpn->bcghlp", Cc, s_in.astype(cd), preferred_element_type=acc)
    y = y + y_off * jnp.exp(jnp.moveaxis(log_decay_from_start, 2, -1))[..., None]

    if D is not None:
        y = y + D.reshape(g, hg).astype(acc)[None, None, :, :, None, None] * jnp.moveaxis(xc, 2, 4).astype(acc)
    y = jnp.moveaxis(y, 4, 2).reshape(b, nc * Q, nh, P)[:, :L]
    return y.reshape(*batch, L, nh, P).astype(x.dtype)


def ssd_scan(
    x: Float[Array, "*batch L nh P"],
    dt: Float[Array, "*batch L nh"],
    A: Float[Array, " nh"],
    B: Float[Array, "*batch L g n"],
    C: Float[Array, "*batch L g n"],
    *,
    chunk_size: int,
    D: Float[ArrayLike, " nh"] | None = None,
    inter_chunk: Literal["associative", "sequential", "fused"] = "associative",
) -> Float[Array, "*batch L nh P"]:
    """Chunked SSD scan (Mamba-2 Listing 1 with a linear-time inter-chunk step).

    Args:
      x: ``[..., L, nh, P]`` inputs per head.
      dt: ``[..., L, nh]`` step sizes, already ``softplus``'ed (>= 0).
      A: ``[nh]`` decay rates (``-exp(A_log)``, <= 0).
      B, C: ``[..., L, g, n]`` input / output projections per group; ``nh % g == 0``.
      chunk_size: Q, any positive int; L is zero-padded to a multiple of Q internally.
      D: optional ``[nh]`` skip weight (``y += D * x``).
      inter_chunk: ``"associative"`` (``lax.associative_scan``, log depth),
        ``"sequential"`` (``lax.scan`` over stored chunk states) or ``"fused"`` (one
        ``lax.scan`` over chunks doing all the work of a chunk, the state carried; fastest
        on CPU, with ``chunk_size`` 128).

    Returns:
      ``[..., L, nh, P]`` in the dtype of ``x``.
    """
    if inter_chunk not in ("associative", "sequential", "fused"):
        raise ValueError(f"ssd_scan: inter_chunk must be 'associative', 'sequential' or 'fused', got {inter_chunk!r}")
    if inter_chunk == "fused":
        return _ssd_fused(x, dt, A, B, C, chunk_size, D)
    return _ssd_chunked(x, dt, A, B, C, chunk_size, D, inter_chunk)


def ssd_dense(
    x: Float[Array, "*batch L nh P"],
    dt: Float[Array, "*batch L nh"],
    A: Float[Array, " nh"],
    B: Float[Array, "*batch L g n"],
    C: Float[Array, "*batch L g n"],
    *,
    chunk_size: int,
    D: Float[ArrayLike, " nh"] | None = None,
) -> Float[Array, "*batch L nh P"]:
    """Chunked SSD with ``ssd_minimal``'s dense O(chunks^2) inter-chunk einsum (an oracle).

    Same arguments and result as :func:`ssd_scan`.
    """
    return _ssd_chunked(x, dt, A, B, C, chunk_size, D, "dense")


def ssd_sequential(
    x: Float[Array, "*batch L nh P"],
    dt: Float[Array, "*batch L nh"],
    A: Float[Array, " nh"],
    B: Float[Array, "*batch L g n"],
    C: Float[Array, "*batch L g n"],
    *,
    D: Float[ArrayLike, " nh"] | None = None,
) -> Float[Array, "*batch L nh P"]:
    """The SSM recurrence as a ``lax.scan`` over time (the oracle; no chunking).

    ``state_t = exp(dt_t A) state_{t-1} + dt_t x_t B_t^T``, ``y_t = state_t C_t + D x_t``.
    Same arguments and result as :func:`ssd_scan` (without ``chunk_size``).
    """
    _check_inputs(x, dt, A, B, C, D)
    *batch, L, nh, P = x.shape
    g, n = B.shape[-2:]
    hg = nh // g
    acc = _acc_dtype(x.dtype)
    b = math.prod(batch)
    xs = jnp.moveaxis(x.reshape(b, L, g, hg, P).astype(acc), 1, 0)
    dts = jnp.moveaxis(dt.reshape(b, L, g, hg).astype(acc), 1, 0)
    Bs = jnp.moveaxis(B.reshape(b, L, g, n).astype(acc), 1, 0)
    Cs = jnp.moveaxis(C.reshape(b, L, g, n).astype(acc), 1, 0)
    Ag = A.reshape(g, hg).astype(acc)[None]

    def step(state, inputs):  # state: [b, g, hg, P, n]
        x_t, dt_t, B_t, C_t = inputs
        decay = jnp.exp(dt_t * Ag)[..., None, None]
        inject = (dt_t[..., None] * x_t)[..., None] * B_t[:, :, None, None, :]
        state = decay * state + inject
        return state, jnp.einsum("bghpn,bgn->bghp", state, C_t)

    _, ys = jax.lax.scan(step, full_like_varying(xs, (b, g, hg, P, n), 0.0, acc), (xs, dts, Bs, Cs))
    y = jnp.moveaxis(ys, 0, 1)  # [b, L, g, hg, P]
    if D is not None:
        y = y + D.reshape(g, hg).astype(acc)[None, None, :, :, None] * jnp.moveaxis(xs, 0, 1)
    return y.reshape(*batch, L, nh, P).astype(x.dtype)
