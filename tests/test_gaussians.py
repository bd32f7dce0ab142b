"""Feature-mode Gaussian centres against a per-Gaussian NumPy oracle, bounded and free offsets."""

import jax
import numpy as np
import pytest

from llrmpp_jax import config as C
from llrmpp_jax.gaussians import GaussianHead, decode_gaussians
from tests.helpers.typechecks import unchecked


def oracle_means(raw, c2w, intr, s, f, offset_scale, max_dist, grid=False):
    """Loop over every Gaussian: pixel = anchor + offset, centre = o + dist * unit ray. The anchor
    is the patch centre, or with ``grid`` the centre of cell (k // m, k % m) of an m x m split."""
    b, v, h, w, k, _ = raw.shape
    out = np.zeros((b, v, h, w, k, 3))
    m = int(round(np.sqrt(k)))
    for i in np.ndindex(b, v, h, w, k):
        off = raw[i][f : f + 2]
        off = off * s if offset_scale is None else offset_scale * s * np.tanh(off)
        ax, ay = ((i[4] % m + 0.5) * s / m, (i[4] // m + 0.5) * s / m) if grid else (s / 2, s / 2)
        x, y = i[3] * s + ax + off[0], i[2] * s + ay + off[1]
        fx, fy, cx, cy = intr[i[0], i[1]]
        d = c2w[i[0], i[1], :3, :3] @ np.array([(x - cx) / fx, (y - cy) / fy, 1.0])
        dist = max_dist / (1 + np.exp(-raw[i][f + 2]))
        out[i] = c2w[i[0], i[1], :3, 3] + dist * d / np.linalg.norm(d)
    return out.reshape(b, -1, 3)


def _cameras(rng, b, v):
    """Random rigid c2w [b, v, 4, 4] and fixed pinhole intrinsics [b, v, 4], float64."""
    q, _ = np.linalg.qr(rng.normal(size=(b, v, 3, 3)))
    c2w = np.zeros((b, v, 4, 4))
    c2w[..., :3, :3], c2w[..., :3, 3], c2w[..., 3, 3] = q, rng.normal(size=(b, v, 3)), 1.0
    return c2w, np.broadcast_to(np.array([30.0, 28.0, 11.0, 9.0]), (b, v, 4))


@pytest.mark.parametrize("offset_scale", [1.0, 2.5, None])
def test_feature_means_bounded_and_free_offsets(rng, offset_scale):
    cfg = C.GaussianHeadConfig(gaussians_per_token=3, feature_dim=4, offset_scale=offset_scale, max_dist=6.0)
    b, v, h, w, k, s = 1, 2, 2, 3, 3, 8
    raw = rng.normal(size=(b, v, h, w, k, 4 + 2 + 1 + 4 + 1 + 3)) * 2.0  # offsets up to ~6 patches raw
    c2w, intr = _cameras(rng, b, v)
    g = decode_gaussians(raw, c2w, intr, s, cfg)
    np.testing.assert_allclose(
        np.asarray(g.means), oracle_means(raw, c2w, intr, s, 4, offset_scale, 6.0), rtol=1e-10, atol=1e-10
    )


@pytest.mark.parametrize("offset_scale", [1.0, None])
def test_grid_anchors_means(rng, offset_scale):
    cfg = C.GaussianHeadConfig(
        gaussians_per_token=9, feature_dim=4, offset_scale=offset_scale, max_dist=6.0, anchors="grid"
    )
    b, v, h, w, k, s = 1, 2, 2, 3, 9, 6
    raw = rng.normal(size=(b, v, h, w, k, 4 + 2 + 1 + 4 + 1 + 3))
    c2w, intr = _cameras(rng, b, v)
    g = decode_gaussians(raw, c2w, intr, s, cfg)
    np.testing.assert_allclose(
        np.asarray(g.means), oracle_means(raw, c2w, intr, s, 4, offset_scale, 6.0, grid=True), rtol=1e-10, atol=1e-10
    )


def test_grid_anchors_start_on_the_sub_grid(rng):
    """A fresh head with anchors='grid' puts Gaussian k of every token on the centre of its
    cell: projected back through the input camera, each lands on (col*p + (k%m+0.5)p/m, ...),
    at distance max_dist / 2, isotropic with scale exp(scale_bias); features and opacities
    are drawn as with 'centre'."""
    cfg = C.GaussianHeadConfig(gaussians_per_token=16, feature_dim=8, max_dist=5.0, anchors="grid", init_std=None)
    b, v, h, w, p = 1, 2, 3, 2, 8
    tokens = rng.normal(size=(b, v * h * w, 32)).astype(np.float32)
    c2w, intr = (a.astype(np.float32) for a in _cameras(rng, b, v))
    head = GaussianHead(cfg, p)
    params = head.init(jax.random.key(3), tokens, (h, w), c2w, intr)
    g = head.apply(params, tokens, (h, w), c2w, intr)
    means = np.asarray(g.means, np.float64).reshape(b, v, h, w, 16, 3)  # pyright: ignore[reportAttributeAccessIssue] -- flax's apply is typed as maybe (out, variables); without mutable= it is out
    for i in np.ndindex(b, v, h, w, 16):
        rot, t = c2w[i[0], i[1], :3, :3].astype(np.float64), c2w[i[0], i[1], :3, 3]
        x = rot.T @ (means[i] - t)
        fx, fy, cx, cy = intr[i[0], i[1]]
        uv = (fx * x[0] / x[2] + cx, fy * x[1] / x[2] + cy)
        want = (i[3] * p + (i[4] % 4 + 0.5) * 2, i[2] * p + (i[4] // 4 + 0.5) * 2)
        np.testing.assert_allclose(uv, want, atol=2e-4)
        np.testing.assert_allclose(np.linalg.norm(means[i] - t), cfg.max_dist / 2, rtol=1e-5)
    np.testing.assert_allclose(np.asarray(g.scales), np.exp(cfg.scale_bias), rtol=1e-6)  # isotropic, one size  # pyright: ignore[reportAttributeAccessIssue] -- flax's apply is typed as maybe (out, variables); without mutable= it is out
    np.testing.assert_allclose(np.asarray(g.quats), np.broadcast_to([1.0, 0, 0, 0], g.quats.shape), atol=1e-7)  # pyright: ignore[reportAttributeAccessIssue] -- flax's apply is typed as maybe (out, variables); without mutable= it is out
    assert np.std(np.asarray(g.features)) > 0.1 and np.std(np.asarray(g.opacities)) > 0.01  # still drawn  # pyright: ignore[reportAttributeAccessIssue] -- flax's apply is typed as maybe (out, variables); without mutable= it is out


def test_grid_anchors_need_a_square_k():
    with pytest.raises(ValueError, match="square gaussians_per_token"):
        C.GaussianHeadConfig(gaussians_per_token=8, anchors="grid")
    with pytest.raises(ValueError, match="anchors must be"), unchecked():
        C.GaussianHeadConfig(anchors="corner")  # pyright: ignore[reportArgumentType] -- a bad value on purpose: the test wants its error
