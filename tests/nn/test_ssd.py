"""SSD scans (llrmpp_jax/nn/ssd.py) against a plain NumPy recurrence and each other.

Oracles: a NumPy double loop over time (checks the JAX sequential reference itself), the
float64 ``ssd_sequential`` (checks the chunked scan and the dense form), and the float64
sequential reference's gradients (checks the chunked scan's autodiff).
Errors are measured as max|a - b| / max|b| ("relative" below).
"""

import functools

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from llrmpp_jax.nn import ssd as ssd_module
from llrmpp_jax.nn.ssd import segment_sum, ssd_dense, ssd_scan, ssd_sequential
from tests.helpers.typechecks import unchecked


def _rel(a, b) -> float:
    a, b = np.asarray(a, np.float64), np.asarray(b, np.float64)
    return float(np.abs(a - b).max() / np.abs(b).max())


def _inputs(rng, batch, L, nh, P, g, n, dt_range=(1e-3, 1.0), dtype=np.float32):
    """Random SSD inputs: dt log-uniform in ``dt_range``, A = -U(1, 16) as Long-LRM's init."""
    x = rng.standard_normal((*batch, L, nh, P))
    dt = np.exp(rng.uniform(np.log(dt_range[0]), np.log(dt_range[1]), (*batch, L, nh)))
    A = -rng.uniform(1.0, 16.0, nh)
    B = rng.standard_normal((*batch, L, g, n))
    C = rng.standard_normal((*batch, L, g, n))
    D = rng.standard_normal(nh)
    return tuple(a.astype(dtype) for a in (x, dt, A, B, C, D))


def _f64(*arrays):
    return tuple(jnp.asarray(np.asarray(a, np.float64)) for a in arrays)


def _numpy_recurrence(x, dt, A, B, C, D):
    """h_t = exp(dt_t A) h_{t-1} + dt_t x_t B_t^T; y_t = h_t C_t + D x_t (float64 loops)."""
    x, dt, A, B, C, D = (np.asarray(a, np.float64) for a in (x, dt, A, B, C, D))
    bsz, L, nh, P = x.shape
    g, n = B.shape[-2:]
    y = np.zeros_like(x)
    for b in range(bsz):
        for h in range(nh):
            gi = h // (nh // g)
            state = np.zeros((P, n))
            for t in range(L):
                state = np.exp(dt[b, t, h] * A[h]) * state + dt[b, t, h] * np.outer(x[b, t, h], B[b, t, gi])
                y[b, t, h] = state @ C[b, t, gi] + D[h] * x[b, t, h]
    return y


def test_segment_sum_matches_loop(rng):
    a = rng.standard_normal((3, 9))
    got = np.asarray(segment_sum(jnp.asarray(a)))
    want = np.full((3, 9, 9), -np.inf)
    for i in range(9):
        for j in range(i + 1):
            want[:, i, j] = a[:, j + 1 : i + 1].sum(axis=-1)
    np.testing.assert_allclose(got, want, rtol=1e-12, atol=1e-12)


def test_sequential_reference_matches_numpy_loop(rng):
    args = _inputs(rng, (2,), 13, 4, 3, 2, 5, dtype=np.float64)  # pyright: ignore[reportArgumentType] -- any float dtype is taken; the annotation comes from the default
    x, dt, A, B, C, D = args
    got = ssd_sequential(*_f64(x, dt, A, B, C), D=jnp.asarray(D))
    assert _rel(got, _numpy_recurrence(*args)) <= 1e-12


# One jitted oracle, so equal shapes across tests compile once.
_sequential = jax.jit(ssd_sequential)


def _oracle(x, dt, A, B, C, D=None):
    """float64 sequential recurrence on the (exactly upcast) inputs."""
    return _sequential(*_f64(x, dt, A, B, C), D=None if D is None else _f64(D)[0])


@pytest.mark.parametrize(
    "chunk_size, methods",
    [
        (1, ("associative",)),
        (7, ("associative", "sequential", "dense", "fused")),
        (64, ("associative", "dense", "fused")),
        (256, ("associative", "sequential", "fused")),
    ],
)
def test_chunked_matches_sequential(rng, chunk_size, methods):
    """float32 chunked scans (and the dense form) vs float64 recurrence: <= 1e-5 relative.

    L = 300 is not a multiple of 7, 64 or 256, so the zero padding is exercised.
    """
    x, dt, A, B, C, D = _inputs(rng, (2,), 300, 4, 8, 1, 6)
    want = _oracle(x, dt, A, B, C, D)
    for method in methods:
        if method == "dense":
            fn = jax.jit(functools.partial(ssd_dense, chunk_size=chunk_size))
        else:
            fn = jax.jit(functools.partial(ssd_scan, chunk_size=chunk_size, inter_chunk=method))
        got = fn(x, dt, A, B, C, D=D)
        assert got.dtype == jnp.float32 and got.shape == x.shape
        assert _rel(got, want) <= 1e-5, method


@pytest.mark.parametrize("inter_chunk", ["associative", "sequential", "fused"])
@pytest.mark.parametrize("batch, chunk_size", [((), 32), ((2, 3), 5)])
def test_ssd_scan_groups_and_batch_dims(rng, batch, chunk_size, inter_chunk):
    """ngroups 2 (heads 0-2 read group 0, heads 3-5 group 1), no D, 0 or 2 batch dims;
    chunk 32 > L = 19 is a single padded chunk."""
    x, dt, A, B, C, _ = _inputs(rng, batch, 19, 6, 4, 2, 3)
    got = jax.jit(functools.partial(ssd_scan, chunk_size=chunk_size, inter_chunk=inter_chunk))(x, dt, A, B, C)
    want = _numpy_recurrence(
        x.reshape(-1, *x.shape[-3:]),
        dt.reshape(-1, *dt.shape[-2:]),
        A,
        B.reshape(-1, *B.shape[-3:]),
        C.reshape(-1, *C.shape[-3:]),
        np.zeros(6),
    ).reshape(x.shape)
    assert _rel(got, want) <= 1e-5


@pytest.mark.parametrize("inter_chunk", ["associative", "sequential", "fused"])
def test_ssd_scan_extreme_decays(rng, inter_chunk):
    """dt from 1e-4 (almost no decay) to 4 (exp(dt*A) ~ e^-64): chunk exponents reach ~-1e4."""
    x, dt, A, B, C, D = _inputs(rng, (1,), 600, 3, 4, 1, 5, dt_range=(1e-4, 4.0))
    got = jax.jit(functools.partial(ssd_scan, chunk_size=256, inter_chunk=inter_chunk))(x, dt, A, B, C, D=D)
    assert np.isfinite(np.asarray(got)).all()
    assert _rel(got, _oracle(x, dt, A, B, C, D)) <= 1e-5


@pytest.mark.parametrize("inter_chunk", ["associative", "sequential", "fused"])
def test_ssd_scan_gradients_match_sequential(rng, inter_chunk):
    """VJPs of the float32 chunked scan (chunks 7 and 64, L = 90) vs the float64 recurrence's
    VJP: <= 1e-4 relative for each of x, dt, A, B, C, D."""
    x, dt, A, B, C, D = _inputs(rng, (2,), 90, 4, 8, 1, 6)
    cot = rng.standard_normal(x.shape)

    def grads(fn, args, cot_dtype):
        _, vjp = jax.vjp(fn, *args)
        return vjp(jnp.asarray(cot, cot_dtype))

    want = jax.jit(grads, static_argnums=(0, 2))(
        lambda *a: ssd_sequential(*a[:5], D=a[5]), _f64(x, dt, A, B, C, D), jnp.float64
    )
    for chunk_size in (7, 64):
        got = jax.jit(grads, static_argnums=(0, 2))(
            lambda *a: ssd_scan(*a[:5], chunk_size=chunk_size, D=a[5], inter_chunk=inter_chunk),  # noqa: B023  called here
            tuple(jnp.asarray(a) for a in (x, dt, A, B, C, D)),
            jnp.float32,
        )
        for name, g, w in zip("x dt A B C D".split(), got, want):
            assert g.dtype == jnp.float32
            assert _rel(g, w) <= 1e-4, (chunk_size, inter_chunk, name)


@pytest.mark.parametrize("forms", ["per_head", "shared", "shared_wide", "mixed"])
def test_fused_scan_both_diagonal_forms(rng, monkeypatch, forms):
    """The fused scan's two forms of a chunk's diagonal block: each forced on every chunk,
    ``per_head`` (limit -1) and ``shared`` by the heads with the decay factorised (limit inf:
    the whole-sequence branch with no per-chunk choice; decays here span <= 16 * 0.1 * 32 =
    51 nats per chunk); ``shared_wide``: every chunk factorised at the default limit with
    ``dt`` scaled so the widest chunk spans 115 nats (factors near e^+-58, their rounding the
    largest the limit allows); ``mixed``: the last two chunks' ``dt`` 30x larger, so one spans
    > 200 nats, where the shared form's factors would leave float32 and the per-chunk choice
    must take the per-head form. Values <= 1e-5 and VJPs <= 1e-4 relative to the float64
    recurrence, 2 groups, L = 100, chunk 32."""
    x, dt, A, B, C, D = _inputs(rng, (2,), 100, 4, 8, 2, 6, dt_range=(1e-3, 1e-1))

    def spans():  # per chunk: the largest decay (nats) over its tokens after the first, any head
        dA = np.pad(dt * A, [(0, 0), (0, 28), (0, 0)]).reshape(2, 4, 32, 4)
        return -dA[:, :, 1:].sum(axis=2).min(axis=(0, 2))

    if forms == "shared_wide":
        dt *= 115.0 / spans().max()
        assert spans().max() < ssd_module._FACTOR_SPAN
    elif forms == "mixed":
        dt[:, 64:] *= 30.0
        dt[:, 64:] *= max(1.0, 250.0 / spans().max())  # whatever the draw, one chunk spans >= 250 nats
        assert spans().min() < ssd_module._FACTOR_SPAN < 200.0 < spans().max(), spans()
    else:
        monkeypatch.setattr(ssd_module, "_FACTOR_SPAN", {"per_head": -1.0, "shared": np.inf}[forms])
    cot = jnp.asarray(rng.standard_normal(x.shape))

    def value_and_vjp(fn, args):
        y, vjp = jax.vjp(fn, *args)
        return y, vjp(cot.astype(y.dtype))

    fused = functools.partial(ssd_scan, chunk_size=32, inter_chunk="fused")
    got_y, got = jax.jit(value_and_vjp, static_argnums=0)(
        lambda *a: fused(*a[:5], D=a[5]), tuple(jnp.asarray(a) for a in (x, dt, A, B, C, D))
    )
    want_y, want = jax.jit(value_and_vjp, static_argnums=0)(
        lambda *a: ssd_sequential(*a[:5], D=a[5]), _f64(x, dt, A, B, C, D)
    )
    assert _rel(got_y, want_y) <= 1e-5
    for name, g, w in zip("x dt A B C D".split(), got, want):
        assert _rel(g, w) <= 1e-4, name


@pytest.mark.parametrize("inter_chunk", ["associative", "sequential", "fused"])
def test_ssd_scan_bf16_accumulates_in_f32(rng, inter_chunk):
    """bf16 inputs: output in bf16, error at bf16 rounding level (not growing with L)."""
    x, dt, A, B, C, D = _inputs(rng, (1,), 600, 2, 16, 1, 16, dt_range=(1e-3, 1e-1))
    xb, dtb, Bb, Cb = (jnp.asarray(a, jnp.bfloat16) for a in (x, dt, B, C))
    got = jax.jit(functools.partial(ssd_scan, chunk_size=256, inter_chunk=inter_chunk))(xb, dtb, A, Bb, Cb, D=D)
    assert got.dtype == jnp.bfloat16
    assert _rel(got, _oracle(xb, dtb, A, Bb, Cb, D)) <= 2e-2


def test_ssd_bad_inputs_raise(rng):
    x, dt, A, B, C, D = _inputs(rng, (2,), 10, 4, 3, 1, 5)
    with pytest.raises(ValueError, match="dt has shape"), unchecked():
        ssd_scan(x, dt[:, :-1], A, B, C, chunk_size=4)
    with pytest.raises(ValueError, match="A has shape"), unchecked():
        ssd_scan(x, dt, A[:3], B, C, chunk_size=4)
    with pytest.raises(ValueError, match="not a multiple of ngroups"), unchecked():
        ssd_sequential(x, dt, A, np.concatenate([B] * 3, -2), np.concatenate([C] * 3, -2))  # pyright: ignore[reportArgumentType] -- a NumPy array where jax.Array is annotated: both work
    with pytest.raises(ValueError, match="C has shape"), unchecked():
        ssd_dense(x, dt, A, B, C[..., :4], chunk_size=4)
    with pytest.raises(ValueError, match="chunk_size"), unchecked():
        ssd_scan(x, dt, A, B, C, chunk_size=0)
    with pytest.raises(ValueError, match="inter_chunk"), unchecked():
        ssd_scan(x, dt, A, B, C, chunk_size=4, inter_chunk="dense")  # pyright: ignore[reportArgumentType] -- a bad value on purpose: the test wants its error
