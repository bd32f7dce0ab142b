"""Projection of 2D Gaussians (surfels, 2DGS of Huang et al. 2024) for one camera.

A surfel is a planar disk: centre mu, rotation R(q) whose first two columns t_u, t_v span
the plane and whose third column is the normal, and two tangent scales ``(s_u, s_v)``.
A point of the plane is ``mu + u s_u t_u + v s_v t_v``; its kernel is
``exp(-(u^2 + v^2) / 2)``.

Ray transform (the 2DGS paper's homogeneous formulation, eq. 9, as gsplat's
``rasterization_2dgs``): in the camera frame (OpenCV, ``[W | w] = inverse(c2w)[:3]``)
``H = [s_u W t_u | s_v W t_v | W mu + w]`` maps ``(u, v, 1)`` to the camera point, and
``M = K H`` (``K`` the pinhole matrix) to the homogeneous pixel ``(x z, y z, z)``. Its rows
``M0, M1, M2`` are stored. For a pixel centre ``(x, y)`` the planes ``h_u = x M2 - M0`` and
``h_v = y M2 - M1`` (in uv-homogeneous space) hold every uv point seen through it, so their
intersection ``h_u x h_v = (c_x, c_y, c_z)`` gives the ray-splat intersection
``(u, v) = (c_x / c_z, c_y / c_z)`` and its camera depth ``z = M2 . (u, v, 1)``.

Screen quantities, gsplat's:

* ``means2d``: the centre of the projected 1-sigma ellipse ``u^2 + v^2 = 1`` (from its dual
  conic, ``M D M^T`` with ``D = diag(1, 1, -1)``); the low-pass filter is centred here. It
  differs from the projected surfel centre by perspective (a fraction of a pixel for small
  surfels);
* ``normals``: ``W t_w`` (R's third column in the camera frame), negated when it points
  away from the camera (``-n . (W mu + w) < 0``);
* ``depths``: the centre's camera z, the sort key.

Box: the compositor's 2DGS alpha is ``min(alpha_max, o max(G3, G2))`` with the surfel kernel
``G3`` and the filter ``G2 = exp(-|d|^2)`` (d = means2d - pixel; :mod:`.composite_surfel`),
so ``alpha >= alpha_min`` needs ``u^2 + v^2 <= 2 L`` or ``|d|^2 <= L`` with
``L = ln(o / alpha_min)``. ``extents`` are the half-widths, around ``means2d``, of the box
holding both regions (the first is the projected ellipse at ``sqrt(2 L)`` sigma, bounded by
its dual conic as above; the second the disk of radius ``sqrt(L)``), with a slack of 0.1%
plus 0.01 px against rounding. Unlike gsplat's 3.33-sigma boxes cut at 16x16 tiles, every
pixel a surfel can be drawn on is inside its box, so the binned render equals the render
of every pixel against every surfel. A surfel whose ``sqrt(2 L)``-sigma ellipse reaches the
camera plane projects to an unbounded region: its box is the whole canvas.

Culled (``radii == 0``, all outputs 0, zero gradient): centre depth outside
``(near, far)``, a 1-sigma ellipse that reaches the camera plane (``M2_u^2 + M2_v^2 >=
M2_z^2``: its projection is no ellipse), ``o <= alpha_min`` (never drawn), a box off the
canvas, non-finite inputs, an invalid camera, or ``keep`` False. Inputs are sanitised
before use, so no NaN reaches gradients.
"""

from __future__ import annotations

from typing import NamedTuple

import jax.numpy as jnp
from jax import lax

from llrmpp_jax.array_typing import Array, Bool, Float, Int
from llrmpp_jax.splat.config import SplatConfig
from llrmpp_jax.splat.projection import (
    ProjectedGaussians,
    _rotate,
    _world_to_camera,
    quat_to_rotmat,
    sanitise_inputs,
)

# Radii are stored as int32; any larger radius already covers every canvas.
_MAX_RADIUS = 2.0**30
# Relative and absolute slack (pixels) of the boxes against rounding.
_BOX_SLACK_REL, _BOX_SLACK_ABS = 1e-3, 1e-2


class ProjectedSurfels(NamedTuple):
    """Screen-space surfels for one camera; every field is 0 where ``radii == 0``."""

    means2d: Float[Array, "N 2"]  # centre of the projected 1-sigma ellipse (pixels)
    ray_transforms: Float[Array, "N 3 3"]  # rows M0, M1, M2 of M = K H
    normals: Float[Array, "N 3"]  # unit normal in the camera frame, facing the camera
    depths: Float[Array, " N"]  # centre camera z (scene units)
    extents: Float[Array, "N 2"]  # half-widths (x, y) of the box where alpha >= alpha_min can hold
    radii: Int[Array, " N"]  # ceil(max(extents)); 0 = culled


def _dot_scaled(p: Float[Array, "N 3"], q: Float[Array, "N 3"], k2: Float[Array, " N"]) -> Float[Array, " N"]:
    """``p D_k q`` with ``D_k = diag(k2, k2, -1)``: the dual conic's entry of rows p, q for
    the ellipse ``u^2 + v^2 = k2``."""
    return k2 * (p[:, 0] * q[:, 0] + p[:, 1] * q[:, 1]) - p[:, 2] * q[:, 2]


def project_surfels(
    means: Float[Array, "N 3"],
    quats: Float[Array, "N 4"],
    scales: Float[Array, "N 2"],
    opacities: Float[Array, " N"],
    c2w: Float[Array, "4 4"],
    intrinsics: Float[Array, " 4"],
    height: int,
    width: int,
    cfg: SplatConfig = SplatConfig(),
    keep: Bool[Array, " N"] | None = None,
) -> ProjectedSurfels:
    """Project N surfels (world space, linear tangent ``scales``) onto an ``height x width``
    canvas; ``opacities`` (the largest of any copy to be drawn) size the boxes. Computes in
    ``means.dtype``. See the module docstring for the rules."""
    keep = jnp.isfinite(opacities) if keep is None else keep & jnp.isfinite(opacities)
    finite, cam_ok, means, quats, scales, c2w, intrinsics = sanitise_inputs(means, quats, scales, c2w, intrinsics, keep)
    opacities = jnp.where(finite, opacities, 0.0)

    rot_w, trans_w = _world_to_camera(c2w)
    centre = _rotate(rot_w, means) + trans_w[None, :]
    rot = quat_to_rotmat(quats)
    tu, tv, normal = (_rotate(rot_w, rot[:, :, k]) for k in range(3))
    a, b = tu * scales[:, 0:1], tv * scales[:, 1:2]
    fx, fy, cx, cy = intrinsics[0], intrinsics[1], intrinsics[2], intrinsics[3]
    m2 = jnp.stack([a[:, 2], b[:, 2], centre[:, 2]], axis=-1)
    m0 = fx * jnp.stack([a[:, 0], b[:, 0], centre[:, 0]], axis=-1) + cx * m2
    m1 = fy * jnp.stack([a[:, 1], b[:, 1], centre[:, 1]], axis=-1) + cy * m2

    z = centre[:, 2]
    one = jnp.ones_like(z)
    dist = _dot_scaled(m2, m2, one)  # < 0: the 1-sigma ellipse lies in front of the camera
    ok = finite & cam_ok & (z > cfg.near) & (z < cfg.far) & (dist < 0)
    dist = jnp.where(ok, dist, -1.0)
    means2d = jnp.stack([_dot_scaled(m0, m2, one) / dist, _dot_scaled(m1, m2, one) / dist], axis=-1)

    # Boxes: binning only, no gradient.
    mx, my = lax.stop_gradient(means2d[:, 0]), lax.stop_gradient(means2d[:, 1])
    s0, s1, s2 = (lax.stop_gradient(r) for r in (m0, m1, m2))
    s0, s1 = s0 - mx[:, None] * s2, s1 - my[:, None] * s2  # pixel origin at means2d: no cancellation
    level = jnp.log(jnp.maximum(lax.stop_gradient(opacities), 1e-30) / cfg.alpha_min)
    drawn = ok & (level > 0)
    level = jnp.where(drawn, level, 1.0)
    k2 = 2.0 * level
    d22 = _dot_scaled(s2, s2, k2)
    bounded = d22 < 0
    d22 = jnp.where(bounded, d22, -1.0)

    def extent(row):
        off = _dot_scaled(row, s2, k2) / d22  # the k-sigma ellipse's centre, relative to means2d
        half = jnp.sqrt(jnp.maximum(off * off - _dot_scaled(row, row, k2) / d22, 0.0))
        e = jnp.where(bounded, jnp.abs(off) + half, _MAX_RADIUS)
        e = jnp.maximum(e, jnp.sqrt(level)) * (1.0 + _BOX_SLACK_REL) + _BOX_SLACK_ABS
        return jnp.minimum(e, _MAX_RADIUS)

    ex, ey = extent(s0), extent(s1)
    inside = (mx + ex > 0) & (mx - ex < width) & (my + ey > 0) & (my - ey < height)
    visible = drawn & inside
    radius = jnp.minimum(jnp.ceil(jnp.maximum(ex, ey)), _MAX_RADIUS)

    toward = lax.stop_gradient(jnp.sum(normal * centre, axis=-1) < 0)  # -n . centre > 0
    normal = jnp.where(toward[:, None], normal, -normal)
    rays = jnp.stack([m0, m1, m2], axis=1)
    return ProjectedSurfels(
        means2d=jnp.where(visible[:, None], means2d, 0.0),
        ray_transforms=jnp.where(visible[:, None, None], rays, 0.0),
        normals=jnp.where(visible[:, None], normal, 0.0),
        depths=jnp.where(visible, z, 0.0),
        extents=jnp.where(visible[:, None], jnp.stack([ex, ey], axis=-1), 0.0),
        radii=jnp.where(visible, radius, 0.0).astype(jnp.int32),
    )


def as_binnable(surfels: ProjectedSurfels) -> ProjectedGaussians:
    """The fields :func:`~llrmpp_jax.splat.binning.bin_gaussians` reads (centre, depth,
    radius), for binning with ``extents=`` the surfels' boxes; no conic (zeros)."""
    zeros = jnp.zeros_like(surfels.means2d[:, :1]).repeat(3, axis=1)
    return ProjectedGaussians(surfels.means2d, zeros, zeros, surfels.depths, surfels.radii)
