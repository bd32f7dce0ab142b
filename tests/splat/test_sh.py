"""Colour mode: SH basis against scipy's spherical harmonics, ``rasterize(render_mode="RGB")``
against the oracle."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from llrmpp_jax.splat import rasterize
from llrmpp_jax.splat.sh import sh_basis
from tests.helpers.smooth_splat import H, N, W, smooth_scene
from tests.helpers.typechecks import unchecked
from tests.oracles.sh import scipy_real_sh
from tests.oracles.splat import oracle_render


def oracle_colors(means, coeffs, c2w, degree):
    basis = scipy_real_sh(means - c2w[:3, 3], degree)
    nb = (degree + 1) ** 2
    return np.maximum(np.einsum("nk,nkc->nc", basis, coeffs[:, :nb]) + 0.5, 0.0)


@pytest.mark.parametrize("degree", [0, 1, 2, 3])
def test_sh_basis_matches_scipy(rng, degree):
    dirs = rng.normal(size=(200, 3))
    got = np.asarray(sh_basis(jnp.asarray(dirs / np.linalg.norm(dirs, axis=-1, keepdims=True)), degree))
    np.testing.assert_allclose(got, scipy_real_sh(dirs, degree), atol=1e-12)


@pytest.mark.parametrize("sh_degree", [None, 1])
def test_rgb_mode_matches_oracle(rng, sh_degree):
    means, quats, scales, opac, _, c2w, intr = smooth_scene(rng)
    coeffs = rng.normal(size=(N, 16, 3)) * np.concatenate([[1.0], np.full(15, 0.3)])[None, :, None]
    background = rng.uniform(0, 1, 3)
    args = (means, quats, scales, opac, coeffs, c2w, intr, H, W)
    out = rasterize(*args, render_mode="RGB", sh_degree=sh_degree)
    rgb = rasterize(*args, render_mode="RGB", background=background, sh_degree=sh_degree).features
    colors = oracle_colors(means, coeffs, c2w, 3 if sh_degree is None else sh_degree)
    assert np.any(colors == 0.0) and np.any(colors > 0.5)  # the clamp at 0 is exercised
    feats, trans, depth = oracle_render(means, quats, scales, opac, colors, c2w, intr, H, W)  # pyright: ignore[reportAssignmentType] -- with_margin=False: three values
    np.testing.assert_allclose(np.asarray(out.features), feats, atol=1e-8)
    np.testing.assert_allclose(np.asarray(rgb), feats + trans[..., None] * background, atol=1e-8)
    np.testing.assert_allclose(np.asarray(out.depth), depth, atol=1e-8)


def test_rgb_mode_gradient_matches_finite_differences(rng):
    """d rgb / d (coefficients, means): SH evaluation from the camera centre plus splatting."""
    means, quats, scales, opac, _, c2w, intr = smooth_scene(rng)
    coeffs = rng.normal(size=(N, 16, 3)) * 0.1 + np.array([1.0] + [0.0] * 15)[None, :, None]  # colours > 0
    cot = jnp.asarray(rng.normal(size=(H, W, 3)))

    @jax.jit
    def value_and_grad(m, c):
        def loss(m, c):
            return jnp.sum(
                cot
                * rasterize(
                    m, quats, scales, opac, c, c2w, intr, H, W, render_mode="RGB", background=jnp.ones(3)
                ).features
            )

        return jax.value_and_grad(loss, argnums=(0, 1))(m, c)

    m, c = jnp.asarray(means), jnp.asarray(coeffs)
    _, (g_m, g_c) = value_and_grad(m, c)
    h = 1e-6
    for i, (x, g) in enumerate(((m, g_m), (c, g_c))):
        v = jnp.asarray(rng.normal(size=x.shape))
        args_p = [m + h * v, c] if i == 0 else [m, c + h * v]
        args_m = [m - h * v, c] if i == 0 else [m, c - h * v]
        fd = (float(value_and_grad(*args_p)[0]) - float(value_and_grad(*args_m)[0])) / (2 * h)
        ad = float(jnp.sum(g * v))
        assert abs(fd - ad) <= 1e-4 * abs(ad), (i, fd, ad)


def test_rgb_mode_rejects_bad_coefficients(rng):
    means, quats, scales, opac, _, c2w, intr = smooth_scene(rng)
    with pytest.raises(ValueError, match="not a square"):
        rasterize(means, quats, scales, opac, np.zeros((N, 10, 3)), c2w, intr, H, W, render_mode="RGB")
    with pytest.raises(ValueError, match="sh_degree 3"):
        rasterize(means, quats, scales, opac, np.zeros((N, 9, 3)), c2w, intr, H, W, render_mode="RGB", sh_degree=3)
    with pytest.raises(ValueError, match=r"features must have shape \(N, sh, 3\)"), unchecked():
        rasterize(means, quats, scales, opac, np.zeros((N, 16)), c2w, intr, H, W, render_mode="RGB")
