"""Feature-mode Gaussian centres against a per-Gaussian NumPy oracle, bounded and free offsets."""

import numpy as np
import pytest

from llrmpp_jax import config as C
from llrmpp_jax.gaussians import decode_gaussians


def oracle_means(raw, c2w, intr, s, f, offset_scale, max_dist):
    """Loop over every Gaussian: pixel = patch centre + offset, centre = o + dist * unit ray."""
    b, v, h, w, k, _ = raw.shape
    out = np.zeros((b, v, h, w, k, 3))
    for i in np.ndindex(b, v, h, w, k):
        off = raw[i][f:f + 2]
        off = off * s if offset_scale is None else offset_scale * s * np.tanh(off)
        x, y = i[3] * s + s / 2 + off[0], i[2] * s + s / 2 + off[1]
        fx, fy, cx, cy = intr[i[0], i[1]]
        d = c2w[i[0], i[1], :3, :3] @ np.array([(x - cx) / fx, (y - cy) / fy, 1.0])
        dist = max_dist / (1 + np.exp(-raw[i][f + 2]))
        out[i] = c2w[i[0], i[1], :3, 3] + dist * d / np.linalg.norm(d)
    return out.reshape(b, -1, 3)


@pytest.mark.parametrize("offset_scale", [1.0, 2.5, None])
def test_feature_means_bounded_and_free_offsets(rng, offset_scale):
    cfg = C.GaussianHeadConfig(gaussians_per_token=3, feature_dim=4, offset_scale=offset_scale, max_dist=6.0)
    b, v, h, w, k, s = 1, 2, 2, 3, 3, 8
    raw = rng.normal(size=(b, v, h, w, k, 4 + 2 + 1 + 4 + 1 + 3)) * 2.0  # offsets up to ~6 patches raw
    q, _ = np.linalg.qr(rng.normal(size=(b, v, 3, 3)))
    c2w = np.zeros((b, v, 4, 4))
    c2w[..., :3, :3], c2w[..., :3, 3], c2w[..., 3, 3] = q, rng.normal(size=(b, v, 3)), 1.0
    intr = np.broadcast_to(np.array([30.0, 28.0, 11.0, 9.0]), (b, v, 4))
    g = decode_gaussians(raw, c2w, intr, s, cfg)
    np.testing.assert_allclose(np.asarray(g.means), oracle_means(raw, c2w, intr, s, 4, offset_scale, 6.0),
                               rtol=1e-10, atol=1e-10)
