"""The compositor's cumulative products and sums along a chunk against NumPy's."""

import jax.numpy as jnp
import numpy as np
import pytest

from llrmpp_jax.splat.composite import _cumulative


@pytest.mark.parametrize("k", [64, 12, 7, 1])
@pytest.mark.parametrize("exclusive", [False, True])
@pytest.mark.parametrize("reverse", [False, True])
@pytest.mark.parametrize("name", ["multiply", "add"])
def test_matches_numpy(k, exclusive, reverse, name):
    x = np.random.default_rng(k + 2 * exclusive + 4 * reverse).uniform(0.2, 1.0, (3, k, 5))
    op, identity, ref = {"multiply": (jnp.multiply, 1.0, np.cumprod), "add": (jnp.add, 0.0, np.cumsum)}[name]
    got = np.asarray(_cumulative(jnp.asarray(x), op, identity, exclusive=exclusive, reverse=reverse))
    assert got.dtype == np.float64  # tests/conftest.py enables x64
    y = x[:, ::-1] if reverse else x
    expected = ref(y, axis=1)
    if exclusive:
        expected = np.concatenate([np.full_like(y[:, :1], identity), expected[:, :-1]], axis=1)
    expected = expected[:, ::-1] if reverse else expected
    np.testing.assert_allclose(got, expected, rtol=1e-12, atol=0)
