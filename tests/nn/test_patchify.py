"""patchify / unpatchify against a plain NumPy loop oracle, the Long-LRM golden tokens,
and their error messages."""

import numpy as np
import pytest

from llrmpp_jax.nn.patchify import patchify, unpatchify
from tests.helpers.environment import shared_path
from tests.helpers.typechecks import unchecked


def loop_patchify(x: np.ndarray, p: int) -> np.ndarray:
    """Oracle: ``[B, V, H, W, C] -> [B, V*h*w, p*p*C]`` element by element (einops-free)."""
    b, v, hh, ww, c = x.shape
    h, w = hh // p, ww // p
    out = np.zeros((b, v * h * w, p * p * c), x.dtype)
    for bi in range(b):
        for vi in range(v):
            for i in range(h):
                for j in range(w):
                    tok = (vi * h + i) * w + j
                    for ph in range(p):
                        for pw in range(p):
                            for ci in range(c):
                                out[bi, tok, (ph * p + pw) * c + ci] = x[bi, vi, i * p + ph, j * p + pw, ci]
    return out


@pytest.mark.parametrize("p", [1, 2, 4])
def test_patchify_matches_loop_oracle(rng, p):
    x = rng.normal(size=(2, 3, 2 * p, 3 * p, 5)).astype(np.float32)
    got = np.asarray(patchify(x, p))
    np.testing.assert_array_equal(got, loop_patchify(x, p))


@pytest.mark.parametrize("p", [2, 4])
def test_unpatchify_matches_loop_oracle_and_round_trips(rng, p):
    b, v, h, w, c = 2, 2, 3, 2, 3
    tokens = rng.normal(size=(b, v * h * w, p * p * c)).astype(np.float32)
    img = np.asarray(unpatchify(tokens, p, v, h, w))
    assert img.shape == (b, v, h * p, w * p, c)
    # Inverse of the oracle: patchifying the result must give the tokens back exactly.
    np.testing.assert_array_equal(loop_patchify(img, p), tokens)
    np.testing.assert_array_equal(np.asarray(patchify(unpatchify(tokens, p, v, h, w), p)), tokens)


def test_patchify_leading_dims(rng):
    """No batch dim and two batch dims agree with the oracle on the same data."""
    x = rng.normal(size=(2, 3, 2, 8, 12, 3)).astype(np.float32)
    got = np.asarray(patchify(x, 4))
    assert got.shape == (2, 3, 2 * 2 * 3, 48)
    want = loop_patchify(x.reshape(6, 2, 8, 12, 3), 4).reshape(2, 3, 12, 48)
    np.testing.assert_array_equal(got, want)
    np.testing.assert_array_equal(np.asarray(patchify(x[0, 0], 4)), want[0, 0])
    np.testing.assert_array_equal(np.asarray(unpatchify(got, 4, 2, 2, 3)), x)


def test_patchify_golden_long_lrm_tokens():
    """Long-LRM's ``tokenizer_input`` is its per-pixel features patchified with p=8."""
    path = shared_path("golden", "long_lrm_tiny", "outputs.npz")
    with np.load(path) as z:
        pixels, want = z["pixel_features"], z["tokenizer_input"]
    np.testing.assert_array_equal(np.asarray(patchify(pixels, 8)), want)


def test_patchify_errors(rng):
    x = np.zeros((2, 12, 16, 3), np.float32)
    with pytest.raises(ValueError, match=r"H=12, W=16.*\(2, 12, 16, 3\).*p=8"):
        patchify(x, 8)
    with pytest.raises(ValueError, match=r"H=12, W=16"):
        patchify(np.zeros((2, 16, 12, 3), np.float32).transpose(0, 2, 1, 3), 8)
    with pytest.raises(ValueError, match=r"\[\.\.\., V, H, W, C\].*\(16, 16, 3\)"), unchecked():
        patchify(np.zeros((16, 16, 3), np.float32), 8)
    with pytest.raises(ValueError, match="p must be >= 1"):
        patchify(x, 0)


def test_unpatchify_errors():
    tokens = np.zeros((2, 12, 4 * 4 * 3), np.float32)
    with pytest.raises(ValueError, match=r"L=12 tokens, expected v\*h\*w = 2\*2\*2 = 8"):
        unpatchify(tokens, 4, 2, 2, 2)
    with pytest.raises(ValueError, match=r"48 features per token, not a multiple of p\*p = 25"):
        unpatchify(tokens, 5, 2, 2, 3)
    with pytest.raises(ValueError, match=r"\[\.\.\., L, p\*p\*C\]"), unchecked():
        unpatchify(np.zeros((48,), np.float32), 4, 1, 1, 1)
