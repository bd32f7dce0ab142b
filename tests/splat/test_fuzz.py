"""No NaN / Inf in outputs or gradients on 1,024 random scenes, degenerate ones included.

Each scene: 16 Gaussians on a 20x24 canvas seen by a random rigid camera, with zero scales
(all or some axes), scales up to 1e3, opacities exactly 0 and 1, unnormalised and zero
quaternions, Gaussians exactly at the camera centre, behind it and in the near plane.
The oracle here is the invariant itself (finite values, transmittance in [0, 1], alpha
weights summing to 1 - T <= 1). A second set injects non-finite inputs and checks the
masking rule keeps everything finite and gives the masked Gaussians zero gradient.
"""

import jax
import jax.numpy as jnp
import numpy as np
from scipy.spatial.transform import Rotation

from llrmpp_jax.splat import SplatConfig, rasterize

S, N, F, H, W = 1024, 16, 4, 20, 24
CFG = SplatConfig(chunk_size=16)


def _scenes(rng):
    z = rng.uniform(-2.0, 8.0, (S, N))
    xy = rng.normal(size=(S, N, 2)) * np.abs(z)[..., None] * 0.5
    means_c = np.concatenate([xy, z[..., None]], -1)
    pick = rng.random((S, N))
    means_c[pick < 0.05] = 0.0  # exactly at the camera centre
    means_c[(pick >= 0.05) & (pick < 0.1), 2] = 0.01  # exactly on the near plane
    log_s = rng.uniform(-8.0, 1.0, (S, N, 3))
    scales = np.exp(log_s)
    scales[rng.random((S, N, 3)) < 0.1] = 0.0  # some axes degenerate
    scales[rng.random((S, N)) < 0.05] = 0.0  # whole Gaussians degenerate
    scales[rng.random((S, N, 3)) < 0.03] = 1e3
    quats = rng.normal(size=(S, N, 4)) * np.exp(rng.uniform(-7.0, 7.0, (S, N, 1)))
    quats[rng.random((S, N)) < 0.05] = 0.0
    opac = rng.uniform(0.0, 1.0, (S, N))
    opac[rng.random((S, N)) < 0.1] = 0.0
    opac[rng.random((S, N)) < 0.2] = 1.0
    feats = rng.normal(size=(S, N, F))
    feats[..., 0] = 1.0  # this channel renders sum_i w_i, which must equal 1 - T
    rot = Rotation.random(S, random_state=rng).as_matrix()  # pyright: ignore[reportCallIssue] -- scipy still takes random_state; its stubs name only rng
    c2w = np.tile(np.eye(4), (S, 1, 1))
    c2w[:, :3, :3], c2w[:, :3, 3] = rot, rng.normal(size=(S, 3))
    means = np.einsum("sij,snj->sni", rot, means_c) + c2w[:, None, :3, 3]
    f = rng.uniform(5.0, 100.0, (S, 2))
    intr = np.concatenate([f, rng.uniform(0.0, 1.0, (S, 2)) * [W, H]], -1)
    return [jnp.asarray(a, jnp.float32) for a in (means, quats, scales, opac, feats, c2w, intr)]


def _loss(means, quats, scales, opac, feats, c2w, intr):
    out = rasterize(means, quats, scales, opac, feats, c2w, intr, H, W, CFG)
    return jnp.sum(out.features) + jnp.sum(out.transmittance) + jnp.sum(out.depth), out


@jax.jit
def _run(scenes):
    grad = jax.value_and_grad(_loss, argnums=(0, 1, 2, 3, 4), has_aux=True)
    return jax.lax.map(lambda sc: grad(*sc), tuple(scenes), batch_size=128)


def _check_finite(result):
    (_, out), grads = result
    for x in (out.features, out.transmittance, out.depth, *grads):
        assert bool(jnp.all(jnp.isfinite(x)))
    t = np.asarray(out.transmittance)
    assert t.min() >= 0.0 and t.max() <= 1.0
    np.testing.assert_allclose(np.asarray(out.features[..., 0]), 1.0 - t, atol=1e-5)


def test_fuzz_outputs_and_gradients_are_finite(rng):
    scenes = _scenes(rng)
    result = _run(scenes)
    _check_finite(result)
    (_, out), _ = result
    assert int(jnp.sum(out.stats.num_visible)) > S * N // 4  # plenty actually rendered
    assert not bool(jnp.any(out.stats.overflow))


def test_fuzz_nonfinite_inputs_are_masked_with_zero_gradient(rng):
    scenes = _scenes(rng)
    which = rng.integers(0, 5, S)  # input array to corrupt, per scene
    gauss = rng.integers(0, N, S)
    values = rng.choice([np.nan, np.inf, -np.inf], S)
    for k in range(5):
        arr = np.array(scenes[k])
        sel = np.flatnonzero(which == k)
        arr[sel, gauss[sel]] = values[sel, None] if arr.ndim == 3 else values[sel]
        scenes[k] = jnp.asarray(arr)
    result = _run(scenes)
    _check_finite(result)
    (_, out), grads = result
    assert np.all(np.asarray(out.stats.num_nonfinite) >= 1)
    for g in grads:
        g = np.asarray(g)
        bad = g[np.arange(S), gauss]
        assert np.all(bad == 0)  # the masked Gaussian has exactly zero gradient
