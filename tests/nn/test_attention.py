"""Global attention against plain dense NumPy oracles.

The oracles (`dense_attention`, `attention_module_oracle`, in ``tests/oracles/attention.py``)
are written independently of the library: attention as an explicit softmax over all L keys.
"""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from llrmpp_jax.nn.attention import Attention, multi_head_attention
from tests.helpers.typechecks import unchecked
from tests.oracles.attention import attention_module_oracle, dense_attention, randomize, rel_err

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
        f(q),
        f(k),
        f(v),
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


def test_cudnn_gets_bfloat16_from_float32_inputs(rng, monkeypatch):
    """cuDNN's kernel takes only 16-bit inputs (an H200 refused the bf16 training step's
    float32 QK-normed q): float32 q, k, v and bias reach it as bfloat16 and the output comes
    back float32. The kernel itself needs a GPU, so the library call is replaced by its XLA
    path on the same (bf16) arguments; the result is compared with the float64 oracle at
    bf16's accuracy."""
    seen = {}
    library = jax.nn.dot_product_attention

    def fake_cudnn(q, k, v, bias=None, mask=None, implementation=None):
        seen.update(q=q.dtype, k=k.dtype, v=v.dtype, bias=bias.dtype, implementation=implementation)  # pyright: ignore[reportOptionalMemberAccess] -- the test passes a bias
        return library(q, k, v, bias=bias, mask=mask, implementation="xla")

    monkeypatch.setattr(jax.nn, "dot_product_attention", fake_cudnn)
    q, k, v = (rng.normal(size=(2, 9, 2, 8)).astype(np.float32) for _ in range(3))
    bias = rng.normal(size=(2, 9, 9)).astype(np.float32)
    got = multi_head_attention(q, k, v, bias=bias, implementation="cudnn")
    assert seen == dict(q=jnp.bfloat16, k=jnp.bfloat16, v=jnp.bfloat16, bias=jnp.bfloat16, implementation="cudnn")
    assert got.dtype == jnp.float32
    f = lambda a: a.astype(np.float64)  # noqa: E731
    assert rel_err(got, dense_attention(f(q), f(k), f(v), f(bias)[None])) < 3e-2


def test_multi_head_attention_errors():
    q = np.zeros((2, 5, 2, 4), np.float32)
    with pytest.raises(ValueError, match=r"share batch dims, nh and hd"), unchecked():
        multi_head_attention(q, np.zeros((2, 5, 3, 4), np.float32), np.zeros((2, 5, 3, 4), np.float32))
    with pytest.raises(ValueError, match=r"k\.shape == v\.shape"), unchecked():
        multi_head_attention(q, q, np.zeros((2, 6, 2, 4), np.float32))
    with (
        pytest.raises(ValueError, match=r"bias has shape \(2, 5, 4\), expected \[nh, Lq, Lk\] = \(2, 5, 5\)"),
        unchecked(),
    ):
        multi_head_attention(q, q, q, bias=np.zeros((2, 5, 4), np.float32))
    with pytest.raises(ValueError, match=r"mask has shape \(3, 2, 5, 5\)"), unchecked():
        multi_head_attention(q, q, q, mask=np.ones((3, 2, 5, 5), bool))


@pytest.mark.parametrize("qk_norm", [False, True])
def test_attention_module_matches_oracle(key, rng, qk_norm):
    x = rng.normal(size=(2, 9, 24)).astype(np.float32)
    m = Attention(dim=24, head_dim=8, qk_norm=qk_norm)
    params = m.init(key, x)["params"]
    names = {"qkv", "proj"} | ({"q_norm", "k_norm"} if qk_norm else set())
    assert set(params) == names
    assert params["qkv"]["kernel"].shape == (24, 72) and params["proj"]["kernel"].shape == (24, 24)  # pyright: ignore[reportAttributeAccessIssue] -- a leaf of the params tree is an array
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
