"""Tests of the float64 splat oracle itself (``tests/oracles/splat.py``): its rotation
against scipy, and composites worked out by hand."""

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from tests.oracles.splat import oracle_render, oracle_rotmat


def test_oracle_rotation_matches_scipy(rng):
    q = rng.normal(size=(50, 4)) * 3.0
    expect = Rotation.from_quat(q[:, [1, 2, 3, 0]]).as_matrix()  # scipy is (x, y, z, w)
    np.testing.assert_allclose(oracle_rotmat(q), expect, atol=1e-12)


def test_oracle_single_and_stacked_gaussians_by_hand(rng):
    """A pixel-centred Gaussian gives alpha = o there; a stack composites as o1 f1 + (1-o1) o2 f2."""
    height, width = 20, 24
    intr = np.array([30.0, 30.0, 12.0, 10.0])
    o1, o2 = rng.uniform(0.2, 0.8, 2)
    z1, z2 = 2.0, 3.0
    px, py = 5.5, 7.5  # centre of pixel (5, 7)
    means = np.array([[(px - 12) / 30 * z, (py - 10) / 30 * z, z] for z in (z2, z1)])  # far first
    feats = rng.normal(size=(2, 3))
    out, trans, depth = oracle_render(  # pyright: ignore[reportAssignmentType] -- with_margin=False: three values
        means, np.tile([1.0, 0, 0, 0], (2, 1)), np.full((2, 3), 0.05), [o2, o1], feats, np.eye(4), intr, height, width
    )
    np.testing.assert_allclose(out[7, 5], o1 * feats[1] + (1 - o1) * o2 * feats[0], atol=1e-12)
    np.testing.assert_allclose(trans[7, 5], (1 - o1) * (1 - o2), atol=1e-12)
    np.testing.assert_allclose(depth[7, 5], o1 * z1 + (1 - o1) * o2 * z2, atol=1e-12)


def test_oracle_stops_before_transmittance_limit():
    """Two alpha-0.999 Gaussians: the second would take T to 1e-6 <= 1e-4, so it is not used."""
    intr = np.array([30.0, 30.0, 8.5, 8.5])  # the means project onto the centre of pixel (8, 8)
    means = np.array([[0.0, 0.0, 2.0], [0.0, 0.0, 3.0]])
    out, trans, _ = oracle_render(  # pyright: ignore[reportAssignmentType] -- as above
        means,
        np.tile([1.0, 0, 0, 0], (2, 1)),
        np.full((2, 3), 0.1),
        [1.0, 1.0],
        [[1.0], [5.0]],
        np.eye(4),
        intr,
        16,
        16,
    )
    assert trans[8, 8] == pytest.approx(1 - 0.999)
    assert out[8, 8, 0] == pytest.approx(0.999)
