"""Brute-force reference 2DGS splatter: every pixel against every surfel, O(N x pixels).

Independent of the fast path (:mod:`.surfel`, :mod:`.composite_surfel`): no binning, no
ray transform, no custom VJP. Each pixel's ray is intersected with each surfel's plane
geometrically (``t = (n . c) / (n . d)``, then the hit's coordinates along the two scaled
tangents), the screen centre is the projected 1-sigma ellipse's centre from the pixel conic
``C = (K H)^-T diag(1, 1, -1) (K H)^-1`` (``-C[:2, :2]^-1 C[:2, 2]``), and the distortion is
the explicit double sum over pairs. Same semantics as
:func:`llrmpp_jax.splat.rasterize` with ``primitive="2dgs"`` (mode "F"): the fast path's
boxes hold every pixel a surfel can be drawn on, so no tile rule is needed here. Used as the
oracle of forward values and, by autodiff, of gradients.
"""

from __future__ import annotations

from typing import NamedTuple

import jax.numpy as jnp
from jax import lax

from llrmpp_jax.array_typing import Array, Float
from llrmpp_jax.splat.config import SplatConfig

_HIGHEST = lax.Precision.HIGHEST


class ReferenceSurfelRender(NamedTuple):
    features: Float[Array, "H W F"]
    transmittance: Float[Array, "H W"]
    depth: Float[Array, "H W"]  # sum_i w_i z_i
    normals: Float[Array, "H W 3"]
    median_depth: Float[Array, "H W"]
    distortion: Float[Array, "H W"]


def _rotation(quats: Float[Array, "N 4"]) -> Float[Array, "N 3 3"]:
    """``R = (w^2 - |v|^2) I + 2 v v^T + 2 w [v]_x`` of the unit quaternion ``(w, v)``."""
    q = quats / jnp.linalg.norm(quats, axis=-1, keepdims=True)
    w, v = q[:, 0], q[:, 1:]
    zero = jnp.zeros_like(w)
    cross = jnp.stack([zero, -v[:, 2], v[:, 1], v[:, 2], zero, -v[:, 0], -v[:, 1], v[:, 0], zero], axis=-1).reshape(
        -1, 3, 3
    )
    scalar = (w * w - jnp.sum(v * v, axis=-1))[:, None, None] * jnp.eye(3, dtype=q.dtype)[None]
    return scalar + 2.0 * v[:, :, None] * v[:, None, :] + 2.0 * w[:, None, None] * cross


def render_surfels_reference(
    means: Float[Array, "N 3"],
    quats: Float[Array, "N 4"],
    scales: Float[Array, "N 2"],
    opacities: Float[Array, " N"],
    features: Float[Array, "N F"],
    c2w: Float[Array, "4 4"],
    intrinsics: Float[Array, " 4"],
    height: int,
    width: int,
    cfg: SplatConfig = SplatConfig(),
    depth: str = "center",
) -> ReferenceSurfelRender:
    """Render like ``rasterize(..., primitive="2dgs", surfel_depth=depth)`` by brute force.

    For finite inputs, a valid camera and surfels whose 1-sigma ellipse lies in front of
    the camera (others are culled, as the fast path culls them).
    """
    dtype = means.dtype
    view = jnp.linalg.inv(c2w)
    centre = jnp.einsum("ij,nj->ni", view[:3, :3], means, precision=_HIGHEST) + view[None, :3, 3]
    rot_c = jnp.einsum("ij,njk->nik", view[:3, :3], _rotation(quats), precision=_HIGHEST)
    tu, tv, normal = rot_c[:, :, 0], rot_c[:, :, 1], rot_c[:, :, 2]
    normal = jnp.where(jnp.sum(normal * centre, -1, keepdims=True) < 0, normal, -normal)
    fx, fy, cx, cy = intrinsics[0], intrinsics[1], intrinsics[2], intrinsics[3]
    k = jnp.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]], dtype)

    # Screen centre: the centre of the projected ellipse u^2 + v^2 = 1, from its dual conic
    # (K H) D (K H)^T (the point conic's inverse; no inverse taken, which near edge-on is
    # ill-conditioned).
    h = jnp.stack([tu * scales[:, :1], tv * scales[:, 1:], centre], axis=-1)  # columns
    kh = jnp.einsum("ij,njk->nik", k, h, precision=_HIGHEST)
    dual = jnp.einsum("nij,j,nkj->nik", kh, jnp.array([1.0, 1.0, -1.0], dtype), kh, precision=_HIGHEST)
    mean2d = dual[:, :2, 2] / dual[:, 2:, 2]

    z_c = centre[:, 2]
    front = jnp.sqrt(h[:, 2, 0] ** 2 + h[:, 2, 1] ** 2) < z_c  # the 1-sigma ellipse in front of the camera
    visible = front & (z_c > cfg.near) & (z_c < cfg.far) & (opacities > cfg.alpha_min)

    iy, ix = jnp.meshgrid(jnp.arange(height), jnp.arange(width), indexing="ij")
    px, py = ix.reshape(-1).astype(dtype) + 0.5, iy.reshape(-1).astype(dtype) + 0.5
    rays = jnp.stack([(px - cx) / fx, (py - cy) / fy, jnp.ones_like(px)], axis=-1)  # [P, 3], z = 1

    def step(carry, i):
        trans, done = carry
        along = rays @ normal[i]  # n . d
        t = jnp.dot(normal[i], centre[i]) / along  # ray parameter of the hit; its z (d_z = 1)
        hit = t[:, None] * rays - centre[i][None, :]
        u = (hit @ tu[i]) / scales[i, 0]
        v = (hit @ tv[i]) / scales[i, 1]
        r3 = u * u + v * v  # surfel kernel exp(-r3 / 2); filter exp(-r2)
        r2 = (mean2d[i, 0] - px) ** 2 + (mean2d[i, 1] - py) ** 2
        alpha = jnp.minimum(cfg.alpha_max, opacities[i] * jnp.maximum(jnp.exp(-0.5 * r3), jnp.exp(-r2)))
        active = visible[i] & (alpha >= cfg.alpha_min) & ~done
        stop = active & (trans * (1.0 - alpha) <= cfg.t_min)
        use = active & ~stop
        w = jnp.where(use, alpha * trans, 0.0)
        z = jnp.full_like(t, z_c[i]) if depth == "center" else jnp.where(r3 <= 2.0 * r2, t, z_c[i])
        return (jnp.where(use, trans * (1.0 - alpha), trans), done | stop), (w, z, trans, use)

    order = jnp.argsort(jnp.where(visible, z_c, jnp.inf), stable=True)
    init = (jnp.ones((height * width,), dtype), jnp.zeros((height * width,), bool))
    (trans, _), (w, z, t_before, use) = lax.scan(step, init, order)  # [N, P] in depth order

    def canvas(x):
        return x.reshape((height, width) + x.shape[1:])

    feats = jnp.einsum("np,nf->pf", w, features[order], precision=_HIGHEST)
    normals = jnp.einsum("np,nf->pf", w, normal[order], precision=_HIGHEST)
    z_safe = jnp.where(use, z, 0.0)
    depth_acc = jnp.sum(w * z_safe, axis=0)
    n = w.shape[0]
    earlier = jnp.arange(n)[:, None] > jnp.arange(n)[None, :]  # [i, j]: j before i
    pairs = w[:, None, :] * w[None, :, :] * (z_safe[:, None, :] - z_safe[None, :, :])
    distortion = 2.0 * jnp.sum(jnp.where(earlier[:, :, None], pairs, 0.0), axis=(0, 1))
    chosen = use & (t_before > 0.5)
    last = jnp.max(jnp.where(chosen, jnp.arange(n)[:, None], -1), axis=0)
    median = jnp.where(last >= 0, jnp.take_along_axis(z_safe, jnp.maximum(last, 0)[None, :], axis=0)[0], 0.0)
    return ReferenceSurfelRender(
        canvas(feats), canvas(trans), canvas(depth_acc), canvas(normals), canvas(median), canvas(distortion)
    )
