"""The Gaussian depth term (gaussian_depth.py) against the brute-force splatter and a NumPy
area mean feeding the paper's depth loss."""

import jax
import jax.numpy as jnp
import numpy as np

from llrmpp_jax import config as C
from llrmpp_jax.gaussian_depth import gaussian_depth_loss, splatted_depth
from llrmpp_jax.losses import depth_loss
from llrmpp_jax.splat.reference import render_features_reference
from tests.helpers.golden import golden_colour_scene


def test_splatted_depth_and_loss_match_brute_force_and_numpy_area_mean(rng):
    """Expected depth = accumulated z / alpha of ``render_features_reference`` (1e-9, float64)
    at the canvas size H/r; the loss equals ``depth_loss`` on that depth against the r x r
    block means of a random positive ground truth computed in NumPy (1e-9)."""
    _, g, c2w, intr = golden_colour_scene()  # cameras of 32 x 48 images
    cfg = C.tiny()  # feature mode, canvas ratio 2
    r = cfg.decoder.canvas_ratio
    h, w, intr = 64, 96, intr * r  # the canvas is the cameras' own 32 x 48 (the depth loss needs >= 32)
    pred, alpha = jax.jit(splatted_depth, static_argnums=(3, 4, 5))(g, c2w, intr / r, h // r, w // r, cfg)
    for b, t in ((0, 0), (1, 1)):
        _, trans, acc_z = render_features_reference(
            g.means[b],
            g.quats[b],
            g.scales[b],
            g.opacities[b],
            g.features[b, :, :3],
            c2w[b, t],
            intr[b, t] / r,
            h // r,
            w // r,
            cfg.splat,
        )
        want_alpha = 1.0 - np.asarray(trans)
        assert want_alpha.min() > 0.01
        np.testing.assert_allclose(np.asarray(alpha[b, t]), want_alpha, rtol=1e-9, atol=1e-12)
        np.testing.assert_allclose(np.asarray(pred[b, t]), np.asarray(acc_z) / want_alpha, rtol=1e-9, atol=0)

    gt = rng.uniform(0.5, 4.0, size=(2, 2, h, w))
    gt[0, 1, 5, 7] = 0.0  # an invalid pixel masks its whole 2x2 block
    blocks = gt.reshape(2, 2, h // r, r, w // r, r)
    want_gt = np.where((blocks > 0).all(axis=(3, 5)), blocks.mean(axis=(3, 5)), 0.0)
    want, _ = depth_loss(pred, jnp.asarray(want_gt), intr / r)
    got, aux = gaussian_depth_loss(g, c2w, intr, jnp.asarray(gt), cfg)
    np.testing.assert_allclose(float(got), float(want), rtol=1e-9)
    np.testing.assert_allclose(float(aux["alpha"]), float(np.mean(alpha)), rtol=1e-12)
    assert float(aux["num_invalid"]) == 1.0


def test_gaussian_depth_gradient_moves_the_means(rng):
    """Finite, non-zero gradients reach the Gaussian centres (what the term is for)."""
    _, g, c2w, intr = golden_colour_scene()
    cfg = C.tiny()
    one = jax.tree.map(lambda a: a[:1], g)
    gt = jnp.asarray(rng.uniform(0.5, 4.0, size=(1, 1, 64, 96)))

    def loss(means):
        return gaussian_depth_loss(one._replace(means=means), c2w[:1, :1], 2 * intr[:1, :1], gt, cfg)[0]

    grad = np.asarray(jax.jit(jax.grad(loss))(one.means))
    assert np.isfinite(grad).all() and np.abs(grad).max() > 0
