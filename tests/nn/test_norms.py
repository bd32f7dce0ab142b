"""Norms vs torch.nn.functional (independent oracle), float64 and float32/bf16 paths."""

import jax.numpy as jnp
import numpy as np
import pytest
import torch

from llrmpp_jax.nn.norms import layer_norm, rms_norm


@pytest.mark.parametrize("dtype, tol", [(np.float64, 1e-12), (np.float32, 2e-6)])
def test_norms_match_torch(rng, dtype, tol):
    x = (rng.standard_normal((4, 5, 33)) * 3 + 1).astype(dtype)
    s = rng.uniform(0.5, 1.5, 33).astype(dtype)
    tx, ts = torch.tensor(x), torch.tensor(s)
    want_ln = torch.nn.functional.layer_norm(tx, (33,), ts, None, 1e-5).numpy()
    want_rms = torch.nn.functional.rms_norm(tx, (33,), ts, 1e-5).numpy()
    got_ln = np.asarray(layer_norm(jnp.asarray(x), jnp.asarray(s)))
    got_rms = np.asarray(rms_norm(jnp.asarray(x), jnp.asarray(s)))
    assert got_ln.dtype == dtype and got_rms.dtype == dtype
    np.testing.assert_allclose(got_ln, want_ln, atol=tol, rtol=tol)
    np.testing.assert_allclose(got_rms, want_rms, atol=tol, rtol=tol)


def test_bf16_input_is_normalised_in_float32(rng):
    x = rng.standard_normal((8, 64)).astype(np.float32) * 100
    s = np.ones(64, np.float32)
    got = rms_norm(jnp.asarray(x, jnp.bfloat16), jnp.asarray(s, jnp.bfloat16))
    assert got.dtype == jnp.bfloat16
    want = torch.nn.functional.rms_norm(torch.tensor(x), (64,), None, 1e-5).numpy()
    np.testing.assert_allclose(np.asarray(got, np.float32), want, atol=2e-2, rtol=1e-2)
