"""Global and local attention against plain dense NumPy oracles.

The oracles here (`dense_attention`, `oracle_offsets`, `dense_local_mask_bias`,
`attention_module_oracle`) are written independently of the library: offsets by brute
force sorting, neighbour masks by loops over grid positions, attention as an explicit
softmax over all L keys. test_transformer.py imports them.
"""

import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from jax.test_util import check_grads
from scipy.special import erf

from llrmpp_jax.nn.attention import (
    Attention,
    LocalAttention,
    local_attention,
    multi_head_attention,
    neighbour_table,
    relative_position_features,
)

# ---------------------------------------------------------------- oracles (float64 NumPy)


def softmax(x: np.ndarray) -> np.ndarray:
    e = np.exp(x - x.max(axis=-1, keepdims=True))
    return e / e.sum(axis=-1, keepdims=True)


def gelu(x: np.ndarray) -> np.ndarray:
    return 0.5 * x * (1.0 + erf(x / math.sqrt(2.0)))


def rms(x: np.ndarray, scale: np.ndarray, eps: float = 1e-5) -> np.ndarray:
    return x / np.sqrt(np.mean(x * x, axis=-1, keepdims=True) + eps) * scale


def dense_attention(q, k, v, bias=None, mask=None):
    """``[B, Lq, nh, hd]`` queries against all keys; bias/mask broadcast to ``[B, nh, Lq, Lk]``."""
    logits = np.einsum("bqhd,bkhd->bhqk", q, k) / math.sqrt(q.shape[-1])
    if bias is not None:
        logits = logits + bias
    if mask is not None:
        logits = np.where(mask, logits, -np.inf)
    return np.einsum("bhqk,bkhd->bqhd", softmax(logits), v)


def oracle_offsets(k: int) -> list[tuple[int, int]]:
    """The k integer (dy, dx) nearest to the origin, ties by dy then dx (brute force)."""
    cands = [(dy, dx) for dy in range(-k, k + 1) for dx in range(-k, k + 1)]
    return sorted(cands, key=lambda o: (o[0] ** 2 + o[1] ** 2, o[0], o[1]))[:k]


def dense_local_mask_bias(h: int, w: int, offsets, table: np.ndarray):
    """Dense ``[L, L]`` neighbour mask and ``[nh, L, L]`` bias of the k-NN attention.

    ``table[j]`` is the per-head bias of offset ``j``; neighbours outside the grid are
    simply absent (masked).
    """
    n = h * w
    mask = np.zeros((n, n), bool)
    bias = np.zeros((table.shape[1], n, n))
    for y in range(h):
        for x in range(w):
            for j, (dy, dx) in enumerate(offsets):
                if 0 <= y + dy < h and 0 <= x + dx < w:
                    mask[y * w + x, (y + dy) * w + x + dx] = True
                    bias[:, y * w + x, (y + dy) * w + x + dx] = table[j]
    return mask, bias


def oracle_features(offsets) -> np.ndarray:
    rows = []
    for dy, dx in offsets:
        d = math.hypot(dx, dy)
        rows.append([0.0] * 5 if d == 0 else [dx, dy, d, dx / d, dy / d])
    return np.array(rows)


def attention_module_oracle(p, x, head_dim, qk_norm, grid=None, num_neighbours=None, eps=1e-5):
    """Float64 re-computation of Attention / LocalAttention from their params ``p``."""
    p = jax.tree.map(lambda a: np.asarray(a, np.float64), p)
    x = np.asarray(x, np.float64)
    b, n, d = x.shape
    nh = d // head_dim
    qkv = (x @ p["qkv"]["kernel"]).reshape(b, n, 3, nh, head_dim)
    q, k, v = qkv[:, :, 0], qkv[:, :, 1], qkv[:, :, 2]
    if qk_norm:
        q, k = rms(q, p["q_norm"]["scale"], eps), rms(k, p["k_norm"]["scale"], eps)
    bias = mask = None
    if grid is not None:
        offs = oracle_offsets(num_neighbours)
        rb = p["rel_bias"]
        table = gelu(oracle_features(offs) @ rb["fc1"]["kernel"] + rb["fc1"]["bias"]) @ rb["fc2"]["kernel"]
        mask, bias = dense_local_mask_bias(*grid, offs, table)
        mask, bias = mask[None, None], bias[None]
    o = dense_attention(q, k, v, bias, mask)
    return o.reshape(b, n, d) @ p["proj"]["kernel"]


def randomize(params, rng, std=0.3):
    """Replace every param by fresh non-trivial values (norm scales around 1)."""

    def new(path, a):
        name = jax.tree_util.keystr(path)
        vals = rng.normal(size=a.shape)
        vals = 1.0 + 0.2 * vals if "scale" in name else std * vals
        return jnp.asarray(vals, a.dtype)

    return jax.tree_util.tree_map_with_path(new, params)


def rel_err(got, want) -> float:
    return float(np.max(np.abs(np.asarray(got, np.float64) - want)) / np.max(np.abs(want)))


# ---------------------------------------------------------------- global attention


@pytest.mark.parametrize("with_bias", [False, True])
def test_multi_head_attention_matches_dense_oracle(rng, with_bias):
    """float32 inputs vs a float64 oracle on the same values; batch dims (2, 3); Lq != Lk."""
    shape_q, shape_k = (2, 3, 5, 2, 4), (2, 3, 7, 2, 4)
    q = rng.normal(size=shape_q).astype(np.float32)
    k, v = (rng.normal(size=shape_k).astype(np.float32) for _ in range(2))
    bias = mask = None
    if with_bias:
        bias = rng.normal(size=(2, 5, 7)).astype(np.float32)  # shared over the batch
        mask = rng.random((2, 3, 1, 5, 7)) > 0.3  # per batch element, broadcast over heads
        mask[..., 0] = True
    got = multi_head_attention(q, k, v, bias=bias, mask=mask)
    f = lambda a: a.astype(np.float64).reshape(6, *a.shape[2:])  # noqa: E731
    want = dense_attention(
        f(q), f(k), f(v),
        None if bias is None else bias[None].astype(np.float64),
        None if mask is None else mask.reshape(6, 1, 5, 7),
    ).reshape(shape_q)
    assert got.shape == shape_q and got.dtype == jnp.float32
    assert rel_err(got, want) < 2e-6


def test_multi_head_attention_float64_inputs(rng):
    """float64 goes through (the library's float32 softmax limits accuracy to ~1e-7)."""
    q, k, v = (rng.normal(size=(2, 6, 3, 4)) for _ in range(3))
    got = multi_head_attention(jnp.asarray(q), jnp.asarray(k), jnp.asarray(v))
    assert got.dtype == jnp.float64
    assert rel_err(got, dense_attention(q, k, v)) < 1e-6


def test_multi_head_attention_errors():
    q = np.zeros((2, 5, 2, 4), np.float32)
    with pytest.raises(ValueError, match=r"share batch dims, nh and hd"):
        multi_head_attention(q, np.zeros((2, 5, 3, 4), np.float32), np.zeros((2, 5, 3, 4), np.float32))
    with pytest.raises(ValueError, match=r"k\.shape == v\.shape"):
        multi_head_attention(q, q, np.zeros((2, 6, 2, 4), np.float32))
    with pytest.raises(ValueError, match=r"bias has shape \(2, 5, 4\), expected \[nh, Lq, Lk\] = \(2, 5, 5\)"):
        multi_head_attention(q, q, q, bias=np.zeros((2, 5, 4), np.float32))
    with pytest.raises(ValueError, match=r"mask has shape \(3, 2, 5, 5\)"):
        multi_head_attention(q, q, q, mask=np.ones((3, 2, 5, 5), bool))


@pytest.mark.parametrize("qk_norm", [False, True])
def test_attention_module_matches_oracle(key, rng, qk_norm):
    x = rng.normal(size=(2, 9, 24)).astype(np.float32)
    m = Attention(dim=24, head_dim=8, qk_norm=qk_norm)
    params = m.init(key, x)["params"]
    names = {"qkv", "proj"} | ({"q_norm", "k_norm"} if qk_norm else set())
    assert set(params) == names
    assert params["qkv"]["kernel"].shape == (24, 72) and params["proj"]["kernel"].shape == (24, 24)
    params = randomize(params, rng)
    got = m.apply({"params": params}, x)
    assert rel_err(got, attention_module_oracle(params, x, 8, qk_norm)) < 1e-5


def test_attention_init_statistics(key):
    """Dense kernels ~ N(0, 0.02), norm scales 1 (Long-LRM ``_init_weights``)."""
    p = Attention(dim=256, head_dim=64, qk_norm=True).init(key, jnp.zeros((1, 2, 256), jnp.float32))["params"]
    w = np.asarray(p["qkv"]["kernel"])
    assert abs(w.std() - 0.02) < 0.001 and abs(w.mean()) < 0.001
    np.testing.assert_array_equal(np.asarray(p["q_norm"]["scale"]), np.ones(64, np.float32))


def test_attention_errors(key):
    with pytest.raises(ValueError, match=r"dim=24 is not a multiple of head_dim=5"):
        Attention(24, 5, False).init(key, jnp.zeros((1, 3, 24), jnp.float32))
    with pytest.raises(ValueError, match=r"x must be \[\.\.\., L, dim=24\], got shape \(1, 3, 16\)"):
        Attention(24, 8, False).init(key, jnp.zeros((1, 3, 16), jnp.float32))


# ---------------------------------------------------------------- neighbour table


@pytest.mark.parametrize("h,w,k", [(4, 4, 13), (5, 7, 64), (3, 2, 16), (2, 3, 1)])
def test_neighbour_table_matches_brute_force(h, w, k):
    index, valid, offsets = neighbour_table(h, w, k)
    offs = oracle_offsets(k)
    assert offsets.shape == (k, 2) and index.shape == valid.shape == (h * w, k)
    assert index.dtype == np.int32 and valid.dtype == bool
    np.testing.assert_array_equal(offsets, np.array(offs))
    for y in range(h):
        for x in range(w):
            t = y * w + x
            for j, (dy, dx) in enumerate(offs):
                inside = 0 <= y + dy < h and 0 <= x + dx < w
                assert valid[t, j] == inside
                assert index[t, j] == ((y + dy) * w + x + dx if inside else t)


def test_neighbour_table_offsets_are_the_nearest():
    """No excluded offset is strictly nearer than an included one, and (0, 0) is first."""
    _, _, offsets = neighbour_table(6, 6, 64)
    d2 = (offsets.astype(np.int64) ** 2).sum(-1)
    chosen = {tuple(o) for o in offsets.tolist()}
    rest = [dy * dy + dx * dx for dy in range(-9, 10) for dx in range(-9, 10) if (dy, dx) not in chosen]
    assert d2.max() <= min(rest) and tuple(offsets[0]) == (0, 0) and len(chosen) == 64


def test_neighbour_table_errors():
    with pytest.raises(ValueError, match=r"h, w, k must be >= 1, got h=3, w=0, k=4"):
        neighbour_table(3, 0, 4)


def test_relative_position_features(rng):
    offsets = np.array(oracle_offsets(25), np.int32)[rng.permutation(25)]
    got = relative_position_features(offsets)
    assert got.dtype == np.float32
    np.testing.assert_allclose(got, oracle_features(offsets.tolist()), rtol=1e-7, atol=0)
    with pytest.raises(ValueError, match=r"offsets must be \[k, 2\].*\(4, 3\)"):
        relative_position_features(np.zeros((4, 3), np.int32))


# ---------------------------------------------------------------- local attention


@pytest.mark.parametrize("h,w,k", [(5, 6, 13), (4, 5, 16), (3, 4, 64)])
def test_local_attention_equals_dense_masked_attention(rng, h, w, k):
    """float64: gather-based local attention == dense attention with neighbour mask + bias."""
    nh, hd, b = 2, 4, 2
    q, kk, v = (rng.normal(size=(b, h * w, nh, hd)) for _ in range(3))
    table = rng.normal(size=(k, nh))
    index, valid, _ = neighbour_table(h, w, k)
    got = local_attention(
        jnp.asarray(q), jnp.asarray(kk), jnp.asarray(v), jnp.asarray(index), jnp.asarray(valid), jnp.asarray(table)
    )
    mask, bias = dense_local_mask_bias(h, w, oracle_offsets(k), table)
    want = dense_attention(q, kk, v, bias[None], mask[None, None])
    assert got.dtype == jnp.float64
    np.testing.assert_allclose(np.asarray(got), want, rtol=0, atol=1e-12)


def test_local_attention_gradients_finite_differences(rng):
    """Reverse-mode gradients (masked entries included) agree with finite differences."""
    h, w, k, nh, hd = 3, 3, 9, 2, 3
    index, valid, _ = neighbour_table(h, w, k)
    args = [jnp.asarray(rng.normal(size=(h * w, nh, hd))) for _ in range(3)] + [jnp.asarray(rng.normal(size=(k, nh)))]

    def f(q, kk, v, bias):
        return local_attention(q, kk, v, jnp.asarray(index), jnp.asarray(valid), bias)

    check_grads(f, args, order=1, modes=("rev",), atol=1e-6, rtol=1e-6)


def test_local_attention_errors(rng):
    index, valid, _ = neighbour_table(2, 3, 4)
    q = jnp.zeros((6, 2, 4), jnp.float32)
    with pytest.raises(ValueError, match=r"bias has shape \(4, 3\), expected \[kn, nh\] = \(4, 2\)"):
        local_attention(q, q, q, jnp.asarray(index), jnp.asarray(valid), jnp.zeros((4, 3), jnp.float32))
    with pytest.raises(ValueError, match=r"must both be \[L, kn\] with L=5"):
        local_attention(q[:5], q[:5], q[:5], jnp.asarray(index), jnp.asarray(valid), jnp.zeros((4, 2), jnp.float32))
    with pytest.raises(ValueError, match=r"one shape"):
        local_attention(q, q[:5], q, jnp.asarray(index), jnp.asarray(valid), jnp.zeros((4, 2), jnp.float32))


@pytest.mark.parametrize("qk_norm", [False, True])
def test_local_attention_module_matches_oracle(key, rng, qk_norm):
    h, w, k = 4, 5, 16
    x = rng.normal(size=(2, h * w, 16)).astype(np.float32)
    m = LocalAttention(dim=16, head_dim=8, qk_norm=qk_norm, grid=(h, w), num_neighbours=k)
    params = m.init(key, x)["params"]
    assert params["rel_bias"]["fc1"]["kernel"].shape == (5, 32)
    assert params["rel_bias"]["fc1"]["bias"].shape == (32,)
    assert set(params["rel_bias"]["fc2"]) == {"kernel"} and params["rel_bias"]["fc2"]["kernel"].shape == (32, 2)
    params = randomize(params, rng)
    got = m.apply({"params": params}, x)
    want = attention_module_oracle(params, x, 8, qk_norm, grid=(h, w), num_neighbours=k)
    assert rel_err(got, want) < 1e-5


@pytest.mark.parametrize("k", [9, 16])
def test_local_attention_translation_invariance(key, rng, k):
    """Shifting the grid shifts the output, for tokens whose neighbourhood stays inside."""
    big = rng.normal(size=(12, 13, 16)).astype(np.float32)
    h, w, sy, sx = 9, 9, 2, 3
    crops = np.stack([big[:h, :w], big[sy : sy + h, sx : sx + w]]).reshape(2, h * w, 16)
    m = LocalAttention(dim=16, head_dim=4, qk_norm=True, grid=(h, w), num_neighbours=k)
    params = randomize(m.init(key, crops)["params"], rng)
    out = np.asarray(m.apply({"params": params}, crops)).reshape(2, h, w, 16)
    offs = np.array(oracle_offsets(k))
    r = np.abs(offs).max()
    compared = 0
    for i in range(r, h - r - sy):
        for j in range(r, w - r - sx):
            # token (i, j) of crop 2 is token (i + sy, j + sx) of crop 1; both fully interior
            np.testing.assert_allclose(out[1, i, j], out[0, i + sy, j + sx], rtol=0, atol=1e-5)
            compared += 1
    assert compared >= 6
    # Border tokens see different (masked) neighbourhoods, so the shift is not trivially exact there.
    assert np.abs(out[1, 0, 0] - out[0, sy, sx]).max() > 1e-3


def test_local_attention_module_errors(key):
    m = LocalAttention(dim=16, head_dim=8, qk_norm=False, grid=(3, 4), num_neighbours=9)
    with pytest.raises(ValueError, match=r"x has shape \(1, 11, 16\), expected \[\.\.\., h\*w, D\] with h\*w = 3\*4 = 12"):
        m.init(key, jnp.zeros((1, 11, 16), jnp.float32))
