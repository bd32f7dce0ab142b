"""EWA projection against the float64 NumPy oracle (gsplat's formulas) and scipy rotations."""

import jax
import jax.numpy as jnp
import numpy as np
from scipy.spatial.transform import Rotation

from llrmpp_jax.splat import SplatConfig
from llrmpp_jax.splat.projection import project_gaussians, quat_to_rotmat
from tests.oracles.splat import oracle_project, random_scene

H, W, N = 37, 53, 300
_project = jax.jit(project_gaussians, static_argnames=("height", "width", "cfg"))


def _project_np(scene, dtype):
    """Project a ``random_scene`` tuple (opacities and features unused) in ``dtype``."""
    means, quats, scales, _, _, c2w, intr = scene
    args = (jnp.asarray(np.asarray(a, dtype)) for a in (means, quats, scales, c2w, intr))
    return jax.tree.map(np.asarray, _project(*args, height=H, width=W, cfg=SplatConfig()))


def test_quat_to_rotmat_matches_scipy(rng):
    q = rng.normal(size=(64, 4)) * rng.uniform(0.1, 5.0, (64, 1))
    q[0] = 0.0  # zero quaternion: identity, as gsplat's F.normalize gives
    got = np.asarray(jax.jit(quat_to_rotmat)(jnp.asarray(q)))
    np.testing.assert_allclose(got[1:], Rotation.from_quat(q[1:, [1, 2, 3, 0]]).as_matrix(), atol=1e-12)
    np.testing.assert_allclose(got[0], np.eye(3), atol=0)


def test_projection_matches_oracle_float64(rng):
    scene = random_scene(rng, N, 1, H, W)
    got = _project_np(scene, np.float64)
    exp = oracle_project(scene[0], scene[1], scene[2], scene[5], scene[6], H, W)
    vis = exp["visible"]
    assert 0.3 * N < vis.sum() < N  # the scene exercises both kept and culled Gaussians
    np.testing.assert_array_equal(got.radii, exp["radii"].astype(np.int32))
    np.testing.assert_allclose(got.means2d[vis], exp["means2d"][vis], rtol=1e-10, atol=1e-9)
    np.testing.assert_allclose(got.depths[vis], exp["depths"][vis], rtol=1e-12, atol=1e-12)
    scale = np.abs(exp["conics"][vis]).max(-1, keepdims=True)
    np.testing.assert_allclose(got.conics[vis] / scale, exp["conics"][vis] / scale, atol=1e-9)
    # The square-completed form is the same quadratic: a = a, q = b / a, s = c - b^2 / a.
    a, b, c = exp["conics"][vis].T
    np.testing.assert_allclose(got.quad_form[vis, 0], a, rtol=1e-9)
    np.testing.assert_allclose(got.quad_form[vis, 1], b / a, rtol=1e-8, atol=1e-12)
    np.testing.assert_allclose(got.quad_form[vis, 2], c - b * b / a, rtol=1e-6)
    for field in got:
        assert np.all(field[~vis] == 0)  # culled Gaussians are all-zero


def test_projection_float32_close_to_oracle(rng):
    scene = [np.asarray(a, np.float32).astype(np.float64) for a in random_scene(rng, N, 1, H, W, conditioned=True)]
    got = _project_np(scene, np.float32)
    exp = oracle_project(scene[0], scene[1], scene[2], scene[5], scene[6], H, W)
    vis = exp["visible"] & (got.radii > 0)
    # ceil(3 sqrt(lambda_max)) may flip by one where it is within rounding of an integer.
    differ = got.radii != exp["radii"]
    assert differ.sum() <= 1 and np.all(np.abs(got.radii - exp["radii"])[differ] == 1)
    np.testing.assert_allclose(got.means2d[vis], exp["means2d"][vis], rtol=1e-6, atol=1e-4)
    np.testing.assert_allclose(got.depths[vis], exp["depths"][vis], rtol=1e-6)
    scale = np.abs(exp["conics"][vis]).max(-1, keepdims=True)
    np.testing.assert_allclose(got.conics[vis] / scale, exp["conics"][vis] / scale, atol=1e-5)


def test_culling_rules():
    """Each special Gaussian is culled for the stated reason; a control one is kept."""
    intr = np.array([40.0, 40.0, 26.0, 18.0])
    cases = {
        "kept": [0.0, 0.0, 2.0],
        "behind": [0.0, 0.0, -2.0],
        "at camera centre": [0.0, 0.0, 0.0],
        "closer than near": [0.0, 0.0, 0.005],
        "beyond far": [0.0, 0.0, 2e6],
        "off screen": [10.0, 0.0, 2.0],
        "off screen but overlapping": [1.4, 0.0, 2.0],  # centre x = 54 > 53, radius ~19 px
    }
    means = np.array(list(cases.values()))
    scales = np.full((len(cases), 3), 0.05)
    scales[-1] = 0.3
    quats = np.tile([1.0, 0.0, 0.0, 0.0], (len(cases), 1))
    got = _project_np((means, quats, scales, None, None, np.eye(4), intr), np.float64)
    kept = {name: bool(r > 0) for name, r in zip(cases, got.radii)}
    assert kept == {name: name in ("kept", "off screen but overlapping") for name in cases}
    assert np.all(np.isfinite(got.means2d)) and np.all(np.isfinite(got.conics))

    keep = jnp.asarray([False] + [True] * (len(cases) - 1))
    geo = [jnp.asarray(a) for a in (means, quats, scales, np.eye(4))]
    masked = _project(*geo, jnp.asarray(intr), height=H, width=W, cfg=SplatConfig(), keep=keep)
    assert int(masked.radii[0]) == 0 and int(masked.radii[-1]) > 0
    for bad in ([0.0, 40.0, 26.0, 18.0], [40.0, -1.0, 26.0, 18.0], [40.0, 40.0, np.nan, 18.0]):
        none = _project(*geo, jnp.asarray(bad), height=H, width=W, cfg=SplatConfig())
        assert int(jnp.sum(none.radii)) == 0
