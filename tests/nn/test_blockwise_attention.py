"""Blockwise (FlashAttention-2) attention against the library's plain attention.

Oracle: ``jax.nn.dot_product_attention`` (XLA path: full ``[L, L]`` logits and softmax)
on the same float32 values, differentiated by JAX's own autodiff; the blockwise kernel
has its own ``custom_vjp`` backward, so the gradients are an independent check of it.
Inputs pass through QK-norm (RMSNorm with random scales) first, so the gradients of the
QK-norm scales flow through q and k as in the model.

Error measure: ``max |got - want| / max(1, max |want|)`` per output or gradient array.
"""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from llrmpp_jax.config import TransformerConfig
from llrmpp_jax.nn.attention import multi_head_attention
from llrmpp_jax.nn.blockwise_attention import blockwise_attention
from llrmpp_jax.nn.norms import rms_norm
from tests.helpers.typechecks import unchecked

NH, HD = 2, 16


def err(got, want) -> float:
    got, want = np.asarray(got, np.float64), np.asarray(want, np.float64)
    return float(np.max(np.abs(got - want)) / max(1.0, float(np.max(np.abs(want)))))


def attention_vjp(attend, args, cotangent):
    """Output and gradients w.r.t. (q_raw, k_raw, v, q_scale, k_scale[, bias]) of
    ``attend(rms_norm(q_raw) , rms_norm(k_raw), v, bias)``."""

    def f(q_raw, k_raw, v, q_scale, k_scale, bias):
        return attend(rms_norm(q_raw, q_scale), rms_norm(k_raw, k_scale), v, bias)

    out, vjp = jax.vjp(f, *args)
    return out, vjp(cotangent)


def random_inputs(rng, b, lq, lk, with_bias, dtype=np.float32):
    q_raw = rng.normal(size=(b, lq, NH, HD)).astype(dtype)
    k_raw, v = (rng.normal(size=(b, lk, NH, HD)).astype(dtype) for _ in range(2))
    scales = [(1.0 + 0.5 * rng.normal(size=HD)).astype(dtype) for _ in range(2)]
    bias = mask = None
    if with_bias:
        bias = (2.0 * rng.normal(size=(1, NH, lq, lk))).astype(dtype)  # shared over the batch
        mask = rng.random((b, 1, lq, lk)) > 0.4  # per batch element, shared over heads
        mask[0, 0, 0, :] = False  # one all-masked query: library gives mean(v), no gradient
    args = [jnp.asarray(a) for a in (q_raw, k_raw, v, *scales)]
    return args + [None if bias is None else jnp.asarray(bias)], mask


# (L, block_q, block_k): every L in {1, 7, 128, 1000, 4097} with blocks that divide L
# (4097 = 17 * 241) and blocks that do not (including one larger than L).
CASES = [
    (1, 1, 1),
    (1, 4, 8),
    (7, 7, 1),
    (7, 3, 2),
    (128, 32, 64),
    (128, 48, 100),
    (1000, 250, 200),
    (1000, 256, 333),
    (4097, 241, 241),
    (4097, 512, 1024),
]


@pytest.mark.parametrize(
    "length,block_q,block_k,with_bias",
    # A 4097^2 bias/mask would cost more than it shows: bias/mask cases stop at L = 1000.
    [(*c, False) for c in CASES] + [(*c, True) for c in CASES if c[0] < 4097],
)
def test_blockwise_equals_plain_attention(rng, length, block_q, block_k, with_bias):
    """Forward and gradients of q, k, v, both QK-norm scales (and the bias) <= 1e-5."""
    b = 2 if length <= 128 else 1
    args, mask = random_inputs(rng, b, length, length, with_bias)
    mask = None if mask is None else jnp.asarray(mask)
    cot = jnp.asarray(rng.normal(size=(b, length, NH, HD)).astype(np.float32))

    def plain(q, k, v, bias):
        return jax.nn.dot_product_attention(q, k, v, bias=bias, mask=mask, implementation="xla")

    def blocked(q, k, v, bias):
        return blockwise_attention(q, k, v, bias=bias, mask=mask, block_q=block_q, block_k=block_k)

    want, want_grads = jax.jit(lambda a, c: attention_vjp(plain, a, c))(args, cot)
    got, got_grads = jax.jit(lambda a, c: attention_vjp(blocked, a, c))(args, cot)
    assert got.shape == want.shape and got.dtype == jnp.float32
    assert err(got, want) <= 1e-5
    names = ["q", "k", "v", "q_norm_scale", "k_norm_scale", "bias"]
    for name, g, w in zip(names, got_grads, want_grads):
        if w is None:
            assert g is None
            continue
        assert np.all(np.isfinite(np.asarray(g))), name
        assert err(g, w) <= 1e-5, (name, err(g, w))


def test_blockwise_cross_attention_broadcast_bias(rng):
    """Lq != Lk, bias per batch element with a size-1 query axis, mask per head."""
    q, k, v = (jnp.asarray(rng.normal(size=(2, n, NH, HD)).astype(np.float32)) for n in (37, 53, 53))
    bias = jnp.asarray(rng.normal(size=(2, 1, 1, 53)).astype(np.float32))
    mask = jnp.asarray(rng.random((1, NH, 37, 53)) > 0.3)
    cot = jnp.asarray(rng.normal(size=(2, 37, NH, HD)).astype(np.float32))

    def run(fn):
        out, vjp = jax.vjp(fn, q, k, v, bias)
        return out, vjp(cot)

    run = jax.jit(run, static_argnums=0)
    want, wg = run(lambda q, k, v, b: jax.nn.dot_product_attention(q, k, v, bias=b, mask=mask))
    got, gg = run(lambda q, k, v, b: blockwise_attention(q, k, v, bias=b, mask=mask, block_q=8, block_k=16))
    assert err(got, want) <= 1e-5
    for g, w in zip(gg, wg):
        assert g.shape == w.shape and err(g, w) <= 1e-5


def test_blockwise_bfloat16_within_plain_bfloat16_error(rng):
    """bf16 inputs: blockwise's error against float32 attention on the same (bf16-exact)
    values is at the level of plain bf16 attention's own error (at most 2x), forward and
    gradients. Both are ~0.3-1% here and differ only in where bf16 rounding happens:
    over seeds 0-3 the ratio was 0.9-1.15 for the output, q, k and v gradients and
    0.6-1.5 for the QK-norm scale gradients (sums over all tokens, rounded once)."""
    args, _ = random_inputs(rng, 1, 1000, 1000, with_bias=False)
    args16 = [jnp.asarray(a, jnp.bfloat16) for a in args[:5]] + [None]
    args32 = [a.astype(jnp.float32) for a in args16[:5]] + [None]  # pyright: ignore[reportOptionalMemberAccess] -- the first five are arrays
    cot16 = jnp.asarray(rng.normal(size=(1, 1000, NH, HD)), jnp.bfloat16)

    def plain(q, k, v, bias):
        return jax.nn.dot_product_attention(q, k, v, implementation="xla")

    def blocked(q, k, v, bias):
        return blockwise_attention(q, k, v, block_q=128, block_k=96)

    ref, ref_g = jax.jit(lambda a, c: attention_vjp(plain, a, c))(args32, cot16.astype(jnp.float32))
    with jax.numpy_dtype_promotion("standard"):  # the library's bf16 -> f32 logits
        p16, p16_g = jax.jit(lambda a, c: attention_vjp(plain, a, c))(args16, cot16)
    b16, b16_g = jax.jit(lambda a, c: attention_vjp(blocked, a, c))(args16, cot16)
    assert b16.dtype == jnp.bfloat16
    assert err(b16, ref) <= 2.0 * err(p16, ref)
    for g, p, w in zip(b16_g[:5], p16_g[:5], ref_g[:5]):
        assert g.dtype == jnp.bfloat16
        assert err(g, w) <= 2.0 * err(p, w)


def count_equations(jaxpr) -> int:
    """Equations of a jaxpr including those of every nested jaxpr (scan bodies, custom_vjp)."""
    n = 0
    for eqn in jaxpr.eqns:
        n += 1
        for p in eqn.params.values():
            for sub in p if isinstance(p, (tuple, list)) else (p,):
                inner = getattr(sub, "jaxpr", sub)
                if hasattr(inner, "eqns"):
                    n += count_equations(inner)
    return n


def test_blockwise_program_does_not_grow_with_length():
    """The fwd+bwd program is two nested scans: same number of equations at any L."""

    def size(length):
        x = jax.ShapeDtypeStruct((1, length, NH, HD), jnp.float32)
        f = lambda q, k, v: jnp.sum(blockwise_attention(q, k, v, block_q=64, block_k=64))  # noqa: E731
        return count_equations(jax.make_jaxpr(jax.grad(f, argnums=(0, 1, 2)))(x, x, x).jaxpr)

    small = size(640)
    assert small > 20 and small == size(64 * 1000)


def test_multi_head_attention_dispatch(rng):
    """The three implementation names reach their kernels; batch dims fold and unfold."""
    q, k, v = (jnp.asarray(rng.normal(size=(2, 3, 20, NH, HD)).astype(np.float32)) for _ in range(3))
    xla = multi_head_attention(q, k, v, implementation="xla")
    blk = multi_head_attention(q, k, v, implementation="blockwise", block_q=6, block_k=7)
    assert blk.shape == q.shape and err(blk, xla) <= 1e-5


def test_bad_input_one_line():
    q = jnp.zeros((1, 5, NH, HD), jnp.float32)
    cases = [
        (lambda: blockwise_attention(q, q, q, block_q=0), r"block sizes must be >= 1, got block_q=0"),
        (lambda: multi_head_attention(q, q, q, block_k=-1), r"block sizes must be >= 1"),
        (
            lambda: blockwise_attention(q, q, q, mask=jnp.ones((1, NH, 5, 4), bool)),
            r"mask has shape \(1, 2, 5, 4\), expected \[B\|1, nh\|1, Lq\|1, Lk\]",
        ),
        (lambda: multi_head_attention(q, q, q, mask=jnp.ones((NH, 5, 6), bool)), r"mask has shape \(2, 5, 6\)"),
        (
            lambda: multi_head_attention(q, q, q, implementation="flash"),  # pyright: ignore[reportArgumentType] -- a bad value on purpose: the test wants its error
            r"implementation must be one of \('xla', 'cudnn', 'blockwise', 'splash'\), got 'flash'",
        ),
        (lambda: TransformerConfig(attention_impl="pallas"), r"attention_impl must be .* got 'pallas'"),  # pyright: ignore[reportArgumentType] -- a bad value on purpose: the test wants its error
        (lambda: TransformerConfig(attention_block_q=0), r"attention block sizes must be >= 1"),
    ]
    for call, message in cases:
        with pytest.raises(ValueError, match=message) as e, unchecked():
            call()
        assert "\n" not in str(e.value)


@pytest.mark.parametrize("backend,impl", [("gpu", "cudnn"), ("tpu", "splash"), ("cpu", "blockwise")])
def test_for_accelerators_picks_the_kernel_per_backend(backend, impl):
    from llrmpp_jax import config as C

    m = C.for_accelerators(C.tiny(), backend)
    assert m.backbone.transformer.attention_impl == impl and m.decoder.transformer.attention_impl == impl
    assert m.backbone.remat and m.decoder.remat
    assert C.tiny().backbone.transformer.attention_impl == "blockwise"  # the default everywhere


def test_blockwise_inside_shard_map_equals_plain(rng):
    """Under ``shard_map`` over the batch axis (the trainer's data parallelism) the loop
    carries must carry the inputs' device variance; output and gradients vs plain <= 1e-5,
    with a parameter-like (replicated) bias."""
    from jax.sharding import NamedSharding
    from jax.sharding import PartitionSpec as P

    mesh = jax.make_mesh((2,), ("batch",))
    args, _ = random_inputs(rng, 2, 45, 45, with_bias=True)
    cot = jnp.asarray(rng.normal(size=(2, 45, NH, HD)).astype(np.float32))

    def grads(attend):
        def per_device(a, c):
            out, g = attention_vjp(attend, a, c)
            return out, [jax.lax.psum(x, "batch") for x in g[3:]]  # replicated params' grads

        specs = ([P("batch")] * 3 + [P()] * 3, P("batch"))
        fn = jax.shard_map(per_device, mesh=mesh, in_specs=specs, out_specs=(P("batch"), [P()] * 3))
        put = lambda x, s: jax.device_put(x, NamedSharding(mesh, s))  # noqa: E731
        return jax.jit(fn)([put(a, s) for a, s in zip(args, specs[0])], put(cot, P("batch")))

    want, want_g = grads(lambda q, k, v, b: jax.nn.dot_product_attention(q, k, v, bias=b, implementation="xla"))
    got, got_g = grads(lambda q, k, v, b: blockwise_attention(q, k, v, bias=b, block_q=16, block_k=8))
    assert err(got, want) <= 1e-5
    for g, w in zip(got_g, want_g):
        assert err(g, w) <= 1e-5
