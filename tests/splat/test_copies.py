"""``rasterize`` with ``[S, N]`` opacities (Long-LRM++'s S partition copies sharing one
projection and binning): values equal S separate renders (and the oracle), gradients of
shared inputs equal the sums over copies."""

import jax
import jax.numpy as jnp
import numpy as np

from llrmpp_jax.splat import rasterize
from tests.helpers import smooth_splat as smooth
from tests.oracles.splat import assert_render_close, oracle_render, random_scene

H, W, N, F = 37, 53, 300, 3


def test_feature_copies_equal_separate_renders(rng):
    means, quats, scales, opac, feats, c2w, intr = random_scene(rng, N, F, H, W)
    copies = np.stack([opac, opac * rng.uniform(0, 1, N)])
    out = rasterize(means, quats, scales, copies, feats, c2w, intr, H, W)
    assert out.features.shape == (2, H, W, F) and out.transmittance.shape == (2, H, W)
    for s in range(2):
        single = rasterize(means, quats, scales, copies[s], feats, c2w, intr, H, W)
        assert_render_close([x[s] for x in out[:3]], single, atol=1e-12)
        assert_render_close(single, oracle_render(means, quats, scales, copies[s], feats, c2w, intr, H, W), atol=1e-8)


def test_copies_grads_equal_sum_of_separate_renders(rng):
    """On the smooth scenes of the gradient tests: shared inputs get the sum over copies."""
    means, quats, scales, opac, feats, c2w, intr = smooth.smooth_scene(rng)
    h, w = smooth.H, smooth.W
    copies = jnp.asarray(np.stack([opac, opac * rng.uniform(0.2, 1.0, smooth.N)]))
    cot = [jnp.asarray(rng.normal(size=(2,) + s)) for s in ((h, w, smooth.F), (h, w), (h, w))]
    args = [jnp.asarray(a) for a in (means, quats, scales)]
    camera = (jnp.asarray(c2w), jnp.asarray(intr))

    def loss_copies(m, q, s, o, f):
        out = rasterize(m, q, s, o, f, jnp.asarray(c2w), jnp.asarray(intr), h, w)
        return sum(jnp.sum(x * g) for x, g in zip(out[:3], cot))

    got = jax.jit(jax.grad(loss_copies, argnums=tuple(range(5))))(*args, copies, jnp.asarray(feats))
    per_copy = [
        smooth.value_and_grad(*args, copies[s], jnp.asarray(feats), *camera, [g[s] for g in cot])[1] for s in range(2)
    ]
    for i in (0, 1, 2, 4):  # shared inputs: gradients add up over the copies
        np.testing.assert_allclose(
            np.asarray(got[i]), np.asarray(per_copy[0][i] + per_copy[1][i]), rtol=1e-9, atol=1e-12
        )
    for s in range(2):
        np.testing.assert_allclose(np.asarray(got[3][s]), np.asarray(per_copy[s][3]), rtol=1e-9, atol=1e-12)
