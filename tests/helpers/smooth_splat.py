"""Smooth splat scenes (``H`` x ``W`` pixels, ``N`` Gaussians, ``F`` features): every alpha at
least 0.1 % (relative) away from 1/255, no pixel near the 1e-4 transmittance stop, no alpha
clamped, no screen radius or tile box near an integer boundary, centres inside the field of
view -- so gsplat's piecewise rules cannot switch between the evaluation points of a finite
difference (gsplat's tests stay away from the same thresholds). With the jitted value and
gradient of one render's weighted sum, for the gradient tests of ``splat/``."""

import jax
import jax.numpy as jnp
import numpy as np
from scipy.spatial.transform import Rotation

from llrmpp_jax.splat import rasterize
from tests.oracles.splat import TILE, oracle_project, oracle_render

H, W, N, F = 21, 35, 40, 3


def smooth_scene(rng):
    """A posed random scene satisfying the smoothness conditions above (resampled until so)."""
    while True:
        fx, fy = 0.8 * W, 0.85 * W
        intr = np.array([fx, fy, 0.52 * W, 0.47 * H])
        z = rng.uniform(1.5, 5.0, N)
        u, v = rng.uniform(0.15 * W, 0.85 * W, N), rng.uniform(0.15 * H, 0.85 * H, N)
        means_c = np.stack([(u - intr[2]) / fx * z, (v - intr[3]) / fy * z, z], -1)
        c2w = np.eye(4)
        c2w[:3, :3], c2w[:3, 3] = Rotation.random(random_state=rng).as_matrix(), rng.normal(size=3)  # pyright: ignore[reportCallIssue] -- scipy still takes random_state; its stubs name only rng
        means = means_c @ c2w[:3, :3].T + c2w[:3, 3]
        quats = rng.normal(size=(N, 4))
        scales = np.exp(rng.uniform(-3.0, -1.5, (N, 3)))
        opac = rng.uniform(0.05, 0.6, N)
        feats = rng.normal(size=(N, F))
        scene = (means, quats, scales, opac, feats, c2w, intr)

        proj = oracle_project(means, quats, scales, c2w, intr, H, W)
        a, b, c = proj["conics"].T
        det = a * c - b * b
        sxx, sxy, syy = c / det, -b / det, a / det  # the 2D covariance
        half = 0.5 * (sxx + syy)
        r_exact = 3.0 * np.sqrt(half + np.sqrt(np.maximum(half * half - (sxx * syy - sxy * sxy), 0.01)))
        edges = np.concatenate([(proj["means2d"] + s * proj["radii"][:, None]) / TILE for s in (-1, 1)], -1)
        *_, margin = oracle_render(*scene, H, W, with_margin=True)
        if (
            proj["visible"].all()
            and np.min(np.abs(r_exact - np.round(r_exact))) > 1e-3
            and np.min(np.abs(edges - np.round(edges))) > 1e-4
            and margin.min() > 1e-3
        ):
            return scene


def _loss(means, quats, scales, opac, feats, c2w, intr, cot):
    """sum(cot * (features, transmittance, depth)) of one render (cot: the cotangents)."""
    d = means.dtype
    out = rasterize(means, quats, scales, opac, feats, c2w.astype(d), intr.astype(d), H, W)
    return sum(jnp.sum(x * g.astype(d)) for x, g in zip(out[:3], cot))


value_and_grad = jax.jit(jax.value_and_grad(_loss, argnums=tuple(range(5))))
