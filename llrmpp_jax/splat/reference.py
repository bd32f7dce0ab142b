"""Brute-force reference splatter: every pixel against every Gaussian, O(N x pixels).

Deliberately independent of the fast path (no binning, no chunks, no custom VJP) and
written in gsplat's own formulation (full 3x3 covariances, explicit Jacobian,
``det = a c - b^2``), so it serves as an autodiff oracle for gradients and as the
baseline of :mod:`llrmpp_jax.benchmarks.splat`. Same semantics as
:func:`llrmpp_jax.splat.rasterize` (mode "F"), including gsplat's tile rule: a Gaussian is
evaluated only at pixels whose 16x16 tile lies in its screen box.
"""

from __future__ import annotations

import jax.numpy as jnp
from jax import lax

from llrmpp_jax.array_typing import Array, Float
from llrmpp_jax.splat.config import SplatConfig

_HIGHEST = lax.Precision.HIGHEST


def render_features_reference(
    means: Float[Array, "N 3"],
    quats: Float[Array, "N 4"],
    scales: Float[Array, "N 3"],
    opacities: Float[Array, " N"],
    features: Float[Array, "N F"],
    c2w: Float[Array, "4 4"],
    intrinsics: Float[Array, " 4"],
    height: int,
    width: int,
    cfg: SplatConfig = SplatConfig(),
) -> tuple[Float[Array, "H W F"], Float[Array, "H W"], Float[Array, "H W"]]:
    """``(features, transmittance, depth)`` like :func:`~llrmpp_jax.splat.rasterize`, by brute force.

    Computes in ``means.dtype``; for finite inputs and a valid camera only.
    """
    dtype = means.dtype
    viewmat = jnp.linalg.inv(c2w)
    rot_w, trans_w = viewmat[:3, :3], viewmat[:3, 3]
    means_c = jnp.einsum("ij,nj->ni", rot_w, means, precision=_HIGHEST) + trans_w[None, :]

    q = quats / jnp.maximum(jnp.linalg.norm(quats, axis=-1, keepdims=True), 1e-12)
    w, x, y, z = q[:, 0], q[:, 1], q[:, 2], q[:, 3]
    rot = jnp.stack(
        [
            jnp.stack([1 - 2 * (y**2 + z**2), 2 * (x * y - w * z), 2 * (x * z + w * y)], -1),
            jnp.stack([2 * (x * y + w * z), 1 - 2 * (x**2 + z**2), 2 * (y * z - w * x)], -1),
            jnp.stack([2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x**2 + y**2)], -1),
        ],
        axis=-2,
    )
    cov = jnp.einsum("nij,nj,nkj->nik", rot, scales**2, rot, precision=_HIGHEST)
    cov_c = jnp.einsum("ij,njk,lk->nil", rot_w, cov, rot_w, precision=_HIGHEST)

    fx, fy, cx, cy = intrinsics[0], intrinsics[1], intrinsics[2], intrinsics[3]
    tx, ty, tz = means_c[:, 0], means_c[:, 1], means_c[:, 2]
    valid = (tz > cfg.near) & (tz < cfg.far)
    tz = jnp.where(valid, tz, 1.0)
    tan_fovx, tan_fovy = 0.5 * width / fx, 0.5 * height / fy
    lim_x_pos, lim_x_neg = (width - cx) / fx + 0.3 * tan_fovx, cx / fx + 0.3 * tan_fovx
    lim_y_pos, lim_y_neg = (height - cy) / fy + 0.3 * tan_fovy, cy / fy + 0.3 * tan_fovy
    txc = tz * jnp.clip(tx / tz, -lim_x_neg, lim_x_pos)
    tyc = tz * jnp.clip(ty / tz, -lim_y_neg, lim_y_pos)
    zero = jnp.zeros_like(tz)
    jac = jnp.stack(
        [
            jnp.stack([fx / tz, zero, -fx * txc / tz**2], -1),
            jnp.stack([zero, fy / tz, -fy * tyc / tz**2], -1),
        ],
        axis=-2,
    )
    cov2d = jnp.einsum("nij,njk,nlk->nil", jac, cov_c, jac, precision=_HIGHEST)
    a = cov2d[:, 0, 0] + cfg.eps2d
    b = 0.5 * (cov2d[:, 0, 1] + cov2d[:, 1, 0])
    c = cov2d[:, 1, 1] + cfg.eps2d
    det = a * c - b * b
    valid = valid & (det > 0)
    det = jnp.where(valid, det, 1.0)
    con_a, con_b, con_c = c / det, -b / det, a / det
    half = 0.5 * (a + c)
    radius = jnp.ceil(cfg.radius_sigmas * jnp.sqrt(half + jnp.sqrt(jnp.maximum(half * half - det, 0.01))))
    mx = fx * means_c[:, 0] / tz + cx
    my = fy * means_c[:, 1] / tz + cy
    visible = valid & (mx + radius > 0) & (mx - radius < width) & (my + radius > 0) & (my - radius < height)

    ts = cfg.tile_size
    tiles_y, tiles_x = cfg.tile_grid(height, width)
    x0 = jnp.clip(jnp.floor(mx / ts - radius / ts), 0, tiles_x)
    x1 = jnp.clip(jnp.ceil(mx / ts + radius / ts), 0, tiles_x)
    y0 = jnp.clip(jnp.floor(my / ts - radius / ts), 0, tiles_y)
    y1 = jnp.clip(jnp.ceil(my / ts + radius / ts), 0, tiles_y)

    order = jnp.argsort(jnp.where(visible, means_c[:, 2], jnp.inf), stable=True)
    iy, ix = jnp.meshgrid(jnp.arange(height), jnp.arange(width), indexing="ij")
    px, py = ix.reshape(-1).astype(dtype) + 0.5, iy.reshape(-1).astype(dtype) + 0.5
    ptx, pty = (ix.reshape(-1) // ts).astype(dtype), (iy.reshape(-1) // ts).astype(dtype)
    f_ext = jnp.concatenate([features, means_c[:, 2:3]], axis=-1)

    def step(carry, i):
        trans, done, acc = carry
        in_box = visible[i] & (ptx >= x0[i]) & (ptx < x1[i]) & (pty >= y0[i]) & (pty < y1[i])
        dx, dy = mx[i] - px, my[i] - py
        sigma = 0.5 * (con_a[i] * dx * dx + con_c[i] * dy * dy) + con_b[i] * dx * dy
        alpha = jnp.minimum(cfg.alpha_max, opacities[i] * jnp.exp(-sigma))
        active = in_box & (sigma >= 0) & (alpha >= cfg.alpha_min) & ~done
        nxt = trans * (1.0 - alpha)
        stop = active & (nxt <= cfg.t_min)
        use = active & ~stop
        acc = acc + jnp.where(use, alpha * trans, 0.0)[:, None] * f_ext[i][None, :]
        return (jnp.where(use, nxt, trans), done | stop, acc), None

    init = (
        jnp.ones((height * width,), dtype),
        jnp.zeros((height * width,), bool),
        jnp.zeros((height * width, f_ext.shape[1]), dtype),
    )
    (trans, _, acc), _ = lax.scan(step, init, order)
    f = features.shape[1]
    return (
        acc[:, :f].reshape(height, width, f),
        trans.reshape(height, width),
        acc[:, f].reshape(height, width),
    )
