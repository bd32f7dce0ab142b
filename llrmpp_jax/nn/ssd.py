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
  carrying the state (:func:`_fused_chunks`): the fastest form on CPU (the state stays in
  cache; experiments/results/bench_scan.json).
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

import math
from typing import Literal

import jax
import jax.numpy as jnp

from llrmpp_jax.array_typing import Array, Float
from llrmpp_jax.nn.variance import full_like_varying

InterChunk = Literal["associative", "sequential", "dense", "fused"]


def _acc_dtype(dtype: jnp.dtype) -> jnp.dtype:
    """Accumulation dtype: float64 for float64 inputs (oracles), float32 otherwise."""
    return jnp.dtype(jnp.float64) if dtype == jnp.float64 else jnp.dtype(jnp.float32)


def _check_inputs(x, dt, A, B, C, D) -> None:
    """Raise ``ValueError`` naming the offending argument and the expected shape."""
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


def segment_sum(a: Float[Array, "... T"]) -> Float[Array, "... T T"]:
    """Segment sums ``out[..., i, j] = sum_{k=j+1..i} a[..., k]`` for ``j <= i``, ``-inf`` above.

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


def _compensated_cumsum(a: Float[Array, "... T"]) -> tuple[Float[Array, "... T"], Float[Array, "... T"]]:
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
    chunk_log_decay: Float[Array, "b c g h"],
    chunk_states: Float[Array, "b c g h P n"],
    method: InterChunk,
) -> Float[Array, "b c g h P n"]:
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
        decay = jnp.exp(segment_sum(jnp.moveaxis(chunk_log_decay, 1, -1)))  # [b, g, h, z, c]
        s_out = jnp.einsum("bghzc,bcghpn->bzghpn", decay.astype(chunk_states.dtype), chunk_states)
    else:
        raise ValueError(f"ssd: inter_chunk must be 'associative', 'sequential' or 'dense', got {method!r}")
    # Exclusive: chunk c starts from the state after chunk c-1.
    return jnp.concatenate([jnp.zeros_like(s_out[:, :1]), s_out[:, :-1]], axis=1)


# Score entries ([b, chunks, nh, Q, Q], float32: 4 bytes each) per step of the intra-chunk
# loop: 16 MiB, so the loop's live [Q, Q] blocks are a few times that whatever L is, and
# each step is still a batched matmul of >= one chunk of every head.
_GROUP_SCORES = 1 << 22


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
    matmul's result ~1.7x faster in that layout than transposed to ``[b, c, Q, g, hg, P]``.
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


def _fused_chunks(
    Cc: Float[Array, "b c Q g n"],
    Bc: Float[Array, "b c Q g n"],
    hi: Float[Array, "b c g hg Q"],
    lo: Float[Array, "b c g hg Q"],
    xdt_bt: Float[Array, "b c g hg Q P"],
    xdt_end: Float[Array, "b c Q g hg P"],
    log_decay_from_start: Float[Array, "b c Q g hg"],
    *,
    cd: jnp.dtype,
    acc: jnp.dtype,
) -> Float[Array, "b c g hg Q P"]:
    """Steps 1-4 of :func:`_ssd_chunked` chunk by chunk: one ``lax.scan`` over chunks whose
    carry is the ``[b, g, hg, P, n]`` state entering the chunk. Per chunk: the diagonal
    block, ``y += decay(start->l) C_l . S``, then ``S <- exp(a_c) S + s_c``.

    Same work as the batched form, but no per-chunk states are materialised ([c, nh, P, n]:
    400 MB at L = 65,536, Q = 256) and the state stays in cache between the two state
    matmuls, which on XLA:CPU is what bounds the batched form (bench_scan.json). The step
    is under ``jax.checkpoint``: the backward keeps only the carried states (one per chunk)
    and recomputes each chunk's ``[Q, Q]`` blocks, which measured faster than storing them.
    """
    from_start = jnp.exp(jnp.moveaxis(log_decay_from_start, 2, -1))[..., None]  # [b, c, g, hg, Q, 1]
    chunk_decay = jnp.exp(log_decay_from_start[:, :, -1])[..., None, None]  # [b, c, g, hg, 1, 1]

    @jax.checkpoint
    def step(state, chunk):
        Cq, Bq, hq, lq, xq, xe, fs, decay = chunk
        y = _intra_chunk(Cq[:, None], Bq[:, None], hq[:, None], lq[:, None], xq[:, None], cd=cd, acc=acc)[:, 0]
        y = y + fs * jnp.einsum("blgn,bghpn->bghlp", Cq, state.astype(cd), preferred_element_type=acc)
        state = decay * state + jnp.einsum("blgn,blghp->bghpn", Bq, xe, preferred_element_type=acc)
        return state, y

    b, _, g, hg, _, P = xdt_bt.shape
    state = full_like_varying(xdt_bt, (b, g, hg, P, Cc.shape[-1]), 0.0, acc)
    chunks = (Cc, Bc, hi, lo, xdt_bt, xdt_end, from_start, chunk_decay)
    _, y = jax.lax.scan(step, state, tuple(jnp.moveaxis(t, 1, 0) for t in chunks))
    return jnp.moveaxis(y, 0, 1)


def _ssd_chunked(x, dt, A, B, C, chunk_size: int, D, inter_chunk: InterChunk):
    _check_inputs(x, dt, A, B, C, D)
    if not isinstance(chunk_size, int) or chunk_size < 1:
        raise ValueError(f"ssd: chunk_size must be a positive int, got {chunk_size!r}")
    *batch, L, nh, P = x.shape
    g, n = B.shape[-2:]
    hg = nh // g  # heads per group; head h reads group h // hg (mamba_ssm's repeat order)
    acc, cd = _acc_dtype(x.dtype), x.dtype
    Q = chunk_size
    b = math.prod(batch)
    # Chunks are processed in `groups` equal groups of at most _GROUP_SCORES score entries
    # ([b, chunks, nh, Q, Q]); L is padded to a whole number of groups (< groups extra chunks).
    # The fused form holds one chunk's blocks at a time: no groups.
    needed = -(-L // Q)
    groups = 1 if inter_chunk == "fused" else -(-needed // max(1, _GROUP_SCORES // (b * nh * Q * Q)))
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
    # XLA:CPU emits one batched matmul instead of a strided loop (5-10x faster at paper sizes).
    xdt_bt = jnp.moveaxis(xdt.astype(cd), 2, 4)
    # Chunk states from zero use decay(l->end): the exponent sum_{k>l} dA_k is a reverse
    # exclusive cumsum (no cancellation).
    rev = jnp.flip(jnp.cumsum(jnp.flip(dA, axis=2), axis=2), axis=2)  # sum_{k>=l}
    to_end = jnp.concatenate([rev[:, :, 1:], jnp.zeros_like(rev[:, :, :1])], axis=2)
    xdt_end = (xdt * jnp.exp(to_end)[..., None]).astype(cd)
    log_decay_from_start = jnp.cumsum(dA, axis=2)  # sum_{k<=l} dA_k, [b, c, Q, g, hg]

    if inter_chunk == "fused":
        y = _fused_chunks(Cc, Bc, hi, lo, xdt_bt, xdt_end, log_decay_from_start, cd=cd, acc=acc)
    else:
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
    x: Float[Array, "... L nh P"],
    dt: Float[Array, "... L nh"],
    A: Float[Array, " nh"],
    B: Float[Array, "... L g n"],
    C: Float[Array, "... L g n"],
    *,
    chunk_size: int,
    D: Float[Array, " nh"] | None = None,
    inter_chunk: Literal["associative", "sequential", "fused"] = "associative",
) -> Float[Array, "... L nh P"]:
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
        on CPU, with ``chunk_size`` 64: ``experiments/results/bench_scan.json``).

    Returns:
      ``[..., L, nh, P]`` in the dtype of ``x``.
    """
    if inter_chunk not in ("associative", "sequential", "fused"):
        raise ValueError(
            f"ssd_scan: inter_chunk must be 'associative', 'sequential' or 'fused', got {inter_chunk!r}"
        )
    return _ssd_chunked(x, dt, A, B, C, chunk_size, D, inter_chunk)


def ssd_dense(
    x: Float[Array, "... L nh P"],
    dt: Float[Array, "... L nh"],
    A: Float[Array, " nh"],
    B: Float[Array, "... L g n"],
    C: Float[Array, "... L g n"],
    *,
    chunk_size: int,
    D: Float[Array, " nh"] | None = None,
) -> Float[Array, "... L nh P"]:
    """Chunked SSD with ``ssd_minimal``'s dense O(chunks^2) inter-chunk einsum (an oracle).

    Same arguments and result as :func:`ssd_scan`.
    """
    return _ssd_chunked(x, dt, A, B, C, chunk_size, D, "dense")


def ssd_sequential(
    x: Float[Array, "... L nh P"],
    dt: Float[Array, "... L nh"],
    A: Float[Array, " nh"],
    B: Float[Array, "... L g n"],
    C: Float[Array, "... L g n"],
    *,
    D: Float[Array, " nh"] | None = None,
) -> Float[Array, "... L nh P"]:
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
