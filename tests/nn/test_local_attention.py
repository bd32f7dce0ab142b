"""k-nearest-neighbour local attention against brute-force neighbour sorts and dense oracles.

Oracles, independent of the library: each token's neighbours by sorting *every* grid
token by (squared distance, dy, dx); attention as a dense masked softmax over all L keys
(float64, NumPy for the module, JAX for gradients). The NumPy ones are in
``tests/oracles/local_attention.py`` and ``tests/oracles/attention.py``.
"""

import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from llrmpp_jax.nn.local_attention import (
    LocalAttention,
    local_attention,
    neighbour_table,
    relative_position_features,
)
from tests.helpers.typechecks import unchecked
from tests.oracles.attention import attention_module_oracle, randomize, rel_err
from tests.oracles.local_attention import brute_neighbours, module_mask_bias, oracle_features

GRIDS = [(1, 1), (1, 7), (7, 1), (2, 3), (5, 6), (8, 8), (13, 4), (20, 33)]
KS = [1, 8, 64, 1000]  # 1000 is more than any grid here


# ---------------------------------------------------------------- neighbour table


@pytest.mark.parametrize("h,w", GRIDS)
def test_neighbour_table_matches_brute_force(h, w):
    """Every token: exactly min(k, L) neighbours, the brute-force sort's, in its order."""
    for k in KS:
        index, offset_id, offsets = neighbour_table(h, w, k)
        kn = min(k, h * w)
        assert index.shape == offset_id.shape == (h * w, kn) and index.dtype == offset_id.dtype == np.int32
        want = np.array(brute_neighbours(h, w, k))  # [L, kn, 2]
        np.testing.assert_array_equal(offsets[offset_id], want)
        ty, tx = np.divmod(np.arange(h * w), w)
        np.testing.assert_array_equal(index, (ty[:, None] + want[..., 0]) * w + tx[:, None] + want[..., 1])
        assert len({tuple(o) for o in offsets.tolist()}) == len(offsets)  # the offset table is distinct


def test_neighbour_table_interior_offsets_are_shared():
    """Tokens whose k nearest offsets fit the grid all use offsets[:k] in order (ids 0..k-1)."""
    h, w, k = 20, 33, 64
    _, offset_id, offsets = neighbour_table(h, w, k)
    r = int(np.abs(offsets[:k]).max())  # 4 for k = 64
    ids = offset_id.reshape(h, w, k)
    interior = ids[r : h - r, r : w - r]
    assert interior.size and (interior == np.arange(k)).all()
    assert tuple(offsets[0]) == (0, 0)
    assert (ids[0, 0] != np.arange(k)).any()  # a corner token gets other (in-grid) offsets


def test_neighbour_table_errors():
    with pytest.raises(ValueError, match=r"h, w, k must be >= 1, got h=3, w=0, k=4"):
        neighbour_table(3, 0, 4)


def test_relative_position_features(rng):
    _, _, offsets = neighbour_table(9, 9, 25)
    offsets = offsets[rng.permutation(len(offsets))]
    got = relative_position_features(offsets)
    assert got.dtype == np.float32
    np.testing.assert_allclose(got, oracle_features(offsets.tolist()), rtol=1e-7, atol=0)
    with pytest.raises(ValueError, match=r"offsets must be \[k, 2\].*\(4, 3\)"), unchecked():
        relative_position_features(np.zeros((4, 3), np.int32))


# ---------------------------------------------------------------- local attention


def dense_oracle(h, w, k):
    """JAX dense masked-softmax attention ``[B, L, nh, hd]`` with a per-pair bias ``[L, kn, nh]``."""
    nbrs = brute_neighbours(h, w, k)
    n, kn = h * w, len(nbrs[0])
    rows = np.repeat(np.arange(n), kn)
    cols = np.array([(t // w + dy) * w + t % w + dx for t, offs in enumerate(nbrs) for dy, dx in offs])
    mask = np.zeros((n, n), bool)
    mask[rows, cols] = True

    def f(q, kk, v, pair_bias):
        nh, hd = q.shape[-2:]
        bias = jnp.zeros((nh, n, n), q.dtype).at[:, rows, cols].set(pair_bias.reshape(n * kn, nh).T)
        logits = jnp.einsum("bqhd,bkhd->bhqk", q, kk) / math.sqrt(hd) + bias[None]
        logits = jnp.where(mask[None, None], logits, -jnp.inf)
        return jnp.einsum("bhqk,bkhd->bqhd", jax.nn.softmax(logits, axis=-1), v)

    return f


@pytest.mark.parametrize("h,w,k", [(1, 1, 1), (3, 4, 8), (5, 6, 64), (20, 33, 8)])
def test_local_attention_equals_dense_oracle_with_gradients(rng, h, w, k):
    """float32 and float64 inputs vs the float64 dense oracle: outputs and the gradients of
    q, k, v and the bias (of a random linear functional of the output)."""
    nh, hd, b = 2, 4, 2
    kn = min(k, h * w)
    index, _, _ = neighbour_table(h, w, k)
    args64 = [rng.normal(size=(b, h * w, nh, hd)) for _ in range(3)] + [rng.normal(size=(h * w, kn, nh))]
    probe = rng.normal(size=(b, h * w, nh, hd))
    oracle = dense_oracle(h, w, k)

    def loss(f):
        return lambda *a: jnp.sum(f(*a) * probe.astype(a[0].dtype))

    want = oracle(*map(jnp.asarray, args64))
    want_grads = jax.grad(loss(oracle), argnums=(0, 1, 2, 3))(*map(jnp.asarray, args64))
    mine = lambda q, kk, v, bias: local_attention(q, kk, v, jnp.asarray(index), bias)  # noqa: E731
    for dtype, tol in ((jnp.float64, 1e-12), (jnp.float32, 1e-5)):
        args = [jnp.asarray(a, dtype) for a in args64]
        got = jax.jit(mine)(*args)
        assert got.dtype == dtype
        assert rel_err(got, np.asarray(want)) <= tol
        grads = jax.jit(jax.grad(loss(mine), argnums=(0, 1, 2, 3)))(*args)
        for name, g, wg in zip("q k v bias".split(), grads, want_grads, strict=True):
            assert g.dtype == dtype and g.shape == wg.shape
            # relative to max(|grad|, 1): on a 1x1 grid the q and k gradients are exactly 0
            err = np.max(np.abs(np.asarray(g, np.float64) - np.asarray(wg)))
            assert err <= tol * max(float(np.max(np.abs(wg))), 1.0), (name, dtype, err)


def test_local_attention_bfloat16_close_to_float32(rng):
    """bf16 q/k/v (float32 softmax inside) stay within bf16 rounding of the float32 result."""
    h, w, k, nh, hd = 6, 7, 16, 2, 8
    index, _, _ = neighbour_table(h, w, k)
    q, kk, v = (jnp.asarray(rng.normal(size=(h * w, nh, hd)), jnp.float32) for _ in range(3))
    bias = jnp.asarray(rng.normal(size=(h * w, k, nh)), jnp.float32)
    want = local_attention(q, kk, v, jnp.asarray(index), bias)
    bf = lambda a: a.astype(jnp.bfloat16)  # noqa: E731
    got = local_attention(bf(q), bf(kk), bf(v), jnp.asarray(index), bias)
    assert got.dtype == jnp.bfloat16
    assert rel_err(got.astype(jnp.float32), np.asarray(want, np.float64)) < 3e-2


def test_local_attention_has_no_full_neighbour_gather():
    """XLA's temp memory of one fwd+bwd stays far below a single [L, kn, nh*hd] gather."""
    h, w, k, nh, hd = 32, 32, 64, 4, 16
    index, _, _ = neighbour_table(h, w, k)
    shape = jax.ShapeDtypeStruct((h * w, nh, hd), jnp.float32)
    bias = jax.ShapeDtypeStruct((h * w, k, nh), jnp.float32)

    def step(q, kk, v, b):
        return jax.grad(
            lambda *a: jnp.sum(local_attention(*a[:3], jnp.asarray(index), a[3]) ** 2),  # pyright: ignore[reportCallIssue] -- the unpacked tuple holds the other arguments
            argnums=(0, 1, 2, 3),
        )(q, kk, v, b)

    mem = jax.jit(step).lower(shape, shape, shape, bias).compile().memory_analysis()
    one_gather = h * w * k * nh * hd * 4  # 16.8 MB
    assert mem.temp_size_in_bytes < one_gather / 4, mem.temp_size_in_bytes  # pyright: ignore[reportOptionalMemberAccess] -- memory_analysis() is None only on a backend without it; CPU, GPU and TPU have it


def test_local_attention_errors():
    index, _, _ = neighbour_table(2, 3, 4)
    q = jnp.zeros((6, 2, 4), jnp.float32)
    idx = jnp.asarray(index)
    with (
        pytest.raises(ValueError, match=r"bias has shape \(6, 4, 3\), expected \[L, kn, nh\] = \(6, 4, 2\)"),
        unchecked(),
    ):
        local_attention(q, q, q, idx, jnp.zeros((6, 4, 3), jnp.float32))
    with pytest.raises(ValueError, match=r"must be \[L, kn\] with L=5"), unchecked():
        local_attention(q[:5], q[:5], q[:5], idx, jnp.zeros((5, 4, 2), jnp.float32))
    with pytest.raises(ValueError, match=r"one shape"), unchecked():
        local_attention(q, q[:5], q, idx, jnp.zeros((6, 4, 2), jnp.float32))


# ---------------------------------------------------------------- module


@pytest.mark.parametrize("qk_norm", [False, True])
def test_local_attention_module_matches_oracle(key, rng, qk_norm):
    h, w, k = 4, 5, 16
    x = rng.normal(size=(2, h * w, 16)).astype(np.float32)
    m = LocalAttention(dim=16, head_dim=8, qk_norm=qk_norm, grid=(h, w), num_neighbours=k)
    params = m.init(key, x)["params"]
    assert params["rel_bias"]["fc1"]["kernel"].shape == (5, 32)  # pyright: ignore[reportAttributeAccessIssue] -- a leaf of the params tree is an array
    assert params["rel_bias"]["fc1"]["bias"].shape == (32,)  # pyright: ignore[reportAttributeAccessIssue] -- a leaf of the params tree is an array
    assert set(params["rel_bias"]["fc2"]) == {"kernel"} and params["rel_bias"]["fc2"]["kernel"].shape == (32, 2)  # pyright: ignore[reportAttributeAccessIssue] -- a leaf of the params tree is an array
    params = randomize(params, rng)
    got = m.apply({"params": params}, x)
    want = attention_module_oracle(params, x, 8, qk_norm, module_mask_bias((h, w), k))
    assert rel_err(got, want) < 1e-5


@pytest.mark.parametrize("k", [9, 16])
def test_local_attention_translation_invariance(key, rng, k):
    """A pattern shifted inside the grid gives the shifted output at interior tokens."""
    big = rng.normal(size=(12, 13, 16)).astype(np.float32)
    h, w, sy, sx = 9, 9, 2, 3
    crops = np.stack([big[:h, :w], big[sy : sy + h, sx : sx + w]]).reshape(2, h * w, 16)
    m = LocalAttention(dim=16, head_dim=4, qk_norm=True, grid=(h, w), num_neighbours=k)
    params = randomize(m.init(key, crops)["params"], rng)
    out = np.asarray(m.apply({"params": params}, crops)).reshape(2, h, w, 16)
    r = max(max(abs(dy), abs(dx)) for dy, dx in brute_neighbours(25, 25, k)[12 * 25 + 12])
    compared = 0
    for i in range(r, h - r - sy):
        for j in range(r, w - r - sx):
            # token (i, j) of crop 2 is token (i + sy, j + sx) of crop 1; both fully interior
            np.testing.assert_allclose(out[1, i, j], out[0, i + sy, j + sx], rtol=0, atol=1e-5)
            compared += 1
    assert compared >= 6
    # A border token's neighbourhood differs from its shifted twin's, so the output does too.
    assert np.abs(out[1, 0, 0] - out[0, sy, sx]).max() > 1e-3


def test_local_attention_module_errors(key):
    m = LocalAttention(dim=16, head_dim=8, qk_norm=False, grid=(3, 4), num_neighbours=9)
    with pytest.raises(
        ValueError, match=r"x has shape \(1, 11, 16\), expected \[\.\.\., h\*w, D\] with h\*w = 3\*4 = 12"
    ):
        m.init(key, jnp.zeros((1, 11, 16), jnp.float32))
