"""The fixed 2-D sin-cos positional embedding against a per-token loop of its formula
(``tests/oracles/position_embedding.py``)."""

import numpy as np
import pytest

from llrmpp_jax.nn.position_embedding import sincos_2d
from tests.oracles.position_embedding import sincos_2d_oracle


@pytest.mark.parametrize("h,w,dim", [(1, 1, 4), (3, 5, 8), (17, 30, 64), (68, 120, 256)])
def test_sincos_2d_matches_formula(h, w, dim):
    got = sincos_2d(h, w, dim)
    assert got.shape == (h * w, dim) and got.dtype == np.float32 and not got.flags.writeable
    np.testing.assert_allclose(got, sincos_2d_oracle(h, w, dim), rtol=0, atol=1e-6)
    # distinct tokens get distinct embeddings, at any grid size
    assert len({r.tobytes() for r in got}) == h * w


def test_sincos_2d_errors():
    with pytest.raises(ValueError, match=r"dim a positive multiple of 4, got h=2, w=3, dim=6"):
        sincos_2d(2, 3, 6)
