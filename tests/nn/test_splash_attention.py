"""The Pallas TPU splash-attention path against plain float64 attention, on this CPU.

The kernel runs in Pallas's TPU interpret mode (``pltpu.force_tpu_interpret_mode()``): the
same kernel bodies, block loops and segment-id masking as on a TPU, executed by XLA:CPU.
Oracle: the explicit softmax ``softmax(q k^T / sqrt(hd)) v`` in float64 jnp, differentiated
by JAX's autodiff (the kernel's gradients come from its own backward kernels). Inputs are
fresh random float32 values; token counts that are not multiples of the 128-token blocks
(padded and masked by segment ids), several blocks per axis and Lq != Lk are covered.

Error measure: ``max |got - want| / max |want|`` per output or gradient array.
"""

import jax
import jax.experimental.pallas.tpu as pltpu
import jax.numpy as jnp
import numpy as np
import pytest

from llrmpp_jax.nn.attention import multi_head_attention
from llrmpp_jax.nn.splash_attention import kernel_block, splash_attention
from tests.helpers.typechecks import unchecked


def plain_attention_f64(q, k, v):
    """``[B, Lq, nh, hd]`` x ``[B, Lk, nh, hd]`` -> ``[B, Lq, nh, hd]``, float64, explicit softmax."""
    q, k, v = (jnp.asarray(a, jnp.float64) for a in (q, k, v))
    s = jnp.einsum("bqhd,bkhd->bhqk", q, k) / np.sqrt(q.shape[-1])
    p = jnp.exp(s - s.max(axis=-1, keepdims=True))
    p = p / p.sum(axis=-1, keepdims=True)
    return jnp.einsum("bhqk,bkhd->bqhd", p, v)


def rel(got, want) -> float:
    got, want = np.asarray(got, np.float64), np.asarray(want, np.float64)
    return float(np.max(np.abs(got - want)) / np.max(np.abs(want)))


def value_and_grads(attn, q, k, v, do):
    """Output and (dq, dk, dv) of ``sum(attn(q, k, v) * do)``."""
    out, vjp = jax.vjp(attn, q, k, v)
    return out, vjp(do.astype(out.dtype))


@pytest.mark.parametrize(
    ("lq", "lk"),
    [
        (200, 200),  # ragged self-attention: 2 blocks of 128, 56 padded tokens masked
        (256, 256),  # exact multiple: no segment ids
        (130, 300),  # Lq != Lk, both ragged: 2 x 3 blocks
    ],
)
def test_splash_matches_plain_float64_attention_forward_and_gradients(rng, lq, lk):
    b, nh, hd = 2, 2, 16
    q = rng.normal(size=(b, lq, nh, hd)).astype(np.float32)
    k, v = (rng.normal(size=(b, lk, nh, hd)).astype(np.float32) for _ in range(2))
    do = jnp.asarray(rng.normal(size=(b, lq, nh, hd)))
    splash = jax.jit(lambda q, k, v: splash_attention(q, k, v, block_q=128, block_k=128))
    with pltpu.force_tpu_interpret_mode():
        out, grads = value_and_grads(splash, jnp.asarray(q), jnp.asarray(k), jnp.asarray(v), do)
    q64, k64, v64 = (jnp.asarray(a, jnp.float64) for a in (q, k, v))
    want, want_grads = value_and_grads(plain_attention_f64, q64, k64, v64, do)
    assert out.shape == (b, lq, nh, hd) and out.dtype == jnp.float32
    assert rel(out, want) < 2e-6
    for name, g, w in zip("qkv", grads, want_grads, strict=True):
        assert g.shape == w.shape and g.dtype == jnp.float32, name
        assert rel(g, w) < 5e-6, name


def test_splash_through_multi_head_attention_bfloat16_and_float64(rng):
    """The ``"splash"`` implementation with batch dims (2, 1): bfloat16 inputs at bf16's
    accuracy; float64 inputs computed in float32 (TPUs have no float64) and returned as float64."""
    q, k, v = (rng.normal(size=(2, 1, 150, 2, 16)) for _ in range(3))
    want = plain_attention_f64(*(a.reshape(2, 150, 2, 16) for a in (q, k, v))).reshape(q.shape)
    with pltpu.force_tpu_interpret_mode():
        got16 = multi_head_attention(*(jnp.asarray(a, jnp.bfloat16) for a in (q, k, v)), implementation="splash")
        got64 = multi_head_attention(*(jnp.asarray(a) for a in (q, k, v)), implementation="splash")
    assert got16.dtype == jnp.bfloat16 and got64.dtype == jnp.float64
    assert rel(got16, want) < 3e-2
    assert rel(got64, want) < 2e-6


def test_splash_gradient_inside_shard_map(rng):
    """The trainer's step runs under ``jax.shard_map`` (varying-axes typing on): a weight's
    gradient through the kernel there, pmean'd over a one-device mesh, against the blockwise
    kernel's outside it."""
    mesh = jax.sharding.Mesh(np.asarray(jax.devices()[:1]), ("batch",))
    rep, split = jax.sharding.PartitionSpec(), jax.sharding.PartitionSpec("batch")
    q, k, v = (jnp.asarray(rng.normal(size=(2, 150, 2, 16)).astype(np.float32)) for _ in range(3))
    w = jnp.asarray(rng.normal(size=(16, 16)).astype(np.float32))

    def loss(w, q, k, v, impl):
        return jnp.sum(multi_head_attention(q @ w, k, v, implementation=impl) ** 2)

    per_device = lambda w, q, k, v: jax.lax.pmean(jax.grad(loss)(w, q, k, v, "splash"), "batch")  # noqa: E731
    mapped = jax.jit(jax.shard_map(per_device, mesh=mesh, in_specs=(rep, split, split, split), out_specs=rep))
    with pltpu.force_tpu_interpret_mode():
        got = mapped(w, q, k, v)
    assert rel(got, jax.grad(loss)(w, q, k, v, "blockwise")) < 1e-5


def test_kernel_blocks_are_128_multiples_covering_short_lengths():
    assert kernel_block(512, 261_122) == 512
    assert kernel_block(300, 261_122) == 384
    assert kernel_block(512, 7) == 128
    assert kernel_block(512, 200) == 256


def test_splash_refuses_bias_and_mask():
    q = np.zeros((1, 5, 2, 4), np.float32)
    with pytest.raises(ValueError, match=r"'splash' takes no bias or mask"), unchecked():
        multi_head_attention(q, q, q, mask=np.ones((2, 5, 5), bool), implementation="splash")
