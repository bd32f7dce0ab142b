"""EWA projection of 3D Gaussians to screen-space ellipses (gsplat "classic" semantics).

Camera convention: OpenCV (x right, y down, z forward), ``c2w`` a 4x4 camera-to-world
matrix, intrinsics ``(fx, fy, cx, cy)`` in pixels, pixel centres at integer + 0.5.

For each Gaussian (mean mu, unit quaternion q = (w, x, y, z), scales s):

* camera point ``t = W mu + w`` with ``[W | w] = inverse(c2w)[:3]`` (gsplat's
  ``viewmats``; the exact inverse of the affine map, so a slightly non-orthonormal c2w
  from float32 data gives the same camera as ``torch.inverse``);
* Jacobian of the pinhole map at t, with gsplat's clamp of ``t_x/t_z`` and ``t_y/t_z`` to
  1.3x the field of view (for the Jacobian only; the projected mean is not clamped);
* ``Sigma2d = M M^T + eps2d I`` with ``M = J W R(q) diag(s)`` ([2, 3]); its determinant is
  taken as ``|m0 x m1|^2 + eps2d (|m0|^2 + |m1|^2) + eps2d^2`` (rows m0, m1 of M), which
  equals ``det(Sigma2d)`` exactly but does not cancel catastrophically in float32 for thin,
  large footprints;
* conic = ``inverse(Sigma2d)`` stored as ``(a, b, c)``: the Mahalanobis half-distance of a
  pixel offset d = mean2d - pixel is ``sigma = 0.5 (a dx^2 + c dy^2) + b dx dy``;
* the same quadratic form with the square completed, ``(a, q, s)`` with
  ``sigma = 0.5 (a (dx + q dy)^2 + s dy^2)``, ``q = b / a = -Sigma_xy / Sigma_yy`` and
  ``s = c - b^2 / a = 1 / Sigma_yy``, computed from Sigma2d directly. The compositor uses
  this form: both terms are non-negative, so thin footprints far from their centre do not
  lose ~all float32 digits to cancellation as gsplat's form does (and ``sigma >= 0``);
* screen radius ``ceil(radius_sigmas sqrt(lambda_max))`` with gsplat's ``0.01`` floor on the
  eigenvalue discriminant (capped at 2^30 pixels so it fits int32).

A Gaussian is culled (radius 0, all outputs 0) when its depth is outside ``(near, far)``,
its ellipse box misses the canvas, ``det(Sigma2d) <= 0``, any of its inputs is non-finite,
its footprint is beyond 1e9 pixels (float32 overflow), the camera is invalid (non-finite,
or ``fx <= 0`` / ``fy <= 0``), or ``keep`` is False. Culled Gaussians get exactly zero
gradient; every quantity on the differentiable path is computed from sanitised inputs so no
NaN/Inf can leak into gradients.
"""

from __future__ import annotations

from typing import NamedTuple

import jax.numpy as jnp
from jax import lax

from llrmpp_jax.array_typing import Array, Bool, Float, Int
from llrmpp_jax.splat.config import SplatConfig

# Rows of M longer than this would overflow det(Sigma2d) ~ |M|^4 in float32.
_MAX_FOOTPRINT = 1e9
# Radii are stored as int32; any larger radius already covers every canvas.
_MAX_RADIUS = 2.0**30
# gsplat's F.normalize eps on the quaternion norm.
_QUAT_EPS = 1e-12
# gsplat clamps t_x / t_z to the field of view widened by this fraction (Jacobian only).
_FOV_MARGIN = 0.3


class ProjectedGaussians(NamedTuple):
    """Screen-space Gaussians for one camera; every field is 0 where ``radii == 0``."""

    means2d: Float[Array, "N 2"]  # projected centre (x, y) in pixels
    conics: Float[Array, "N 3"]  # inverse 2D covariance (a, b, c), 1/pixels^2
    quad_form: Float[Array, "N 3"]  # (a, q, s): sigma = 0.5 (a (dx + q dy)^2 + s dy^2)
    depths: Float[Array, " N"]  # camera-space z (scene units)
    radii: Int[Array, " N"]  # screen radius in whole pixels; 0 = culled


def quat_to_rotmat(quats: Float[Array, "N 4"]) -> Float[Array, "N 3 3"]:
    """Rotation matrices from quaternions ``(w, x, y, z)``, normalised inside.

    A zero quaternion maps to the identity (gsplat's ``F.normalize`` behaviour).
    """
    sq = jnp.sum(quats * quats, axis=-1, keepdims=True)
    q = quats * lax.rsqrt(jnp.maximum(sq, _QUAT_EPS**2))
    w, x, y, z = q[:, 0], q[:, 1], q[:, 2], q[:, 3]
    rows = [
        [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
        [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
        [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
    ]
    return jnp.stack([jnp.stack(r, axis=-1) for r in rows], axis=-2)


def camera_is_valid(c2w: Float[Array, "4 4"], intrinsics: Float[Array, " 4"]) -> Bool[Array, ""]:
    """True when the camera is usable: finite entries and positive focal lengths."""
    return jnp.all(jnp.isfinite(c2w)) & jnp.all(jnp.isfinite(intrinsics)) & (intrinsics[0] > 0) & (intrinsics[1] > 0)


def _cross(u: Float[Array, "N 3"], v: Float[Array, "N 3"]) -> Float[Array, "N 3"]:
    return jnp.stack(
        [
            u[:, 1] * v[:, 2] - u[:, 2] * v[:, 1],
            u[:, 2] * v[:, 0] - u[:, 0] * v[:, 2],
            u[:, 0] * v[:, 1] - u[:, 1] * v[:, 0],
        ],
        axis=-1,
    )


def _world_to_camera(c2w: Float[Array, "4 4"]) -> tuple[Float[Array, "3 3"], Float[Array, " 3"]]:
    """``(W, w)`` of ``inverse(c2w) = [[W, w], [0, 1]]`` for an affine ``c2w`` (adjugate formula,
    elementwise: cheaper to compile than a general LU inverse and exact to rounding)."""
    rows = c2w[:3, :3]
    cof = _cross(jnp.roll(rows, -1, axis=0), jnp.roll(rows, -2, axis=0))  # r_{i+1} x r_{i+2}
    det = jnp.sum(rows[0] * cof[0])
    rot_w = cof.T / det
    trans_w = -jnp.sum(rot_w * c2w[:3, 3][None, :], axis=-1)
    return rot_w, trans_w


def _rotate(rot: Float[Array, "3 3"], vecs: Float[Array, "N 3"]) -> Float[Array, "N 3"]:
    """``vecs @ rot.T`` as explicit multiply-adds: exact float32 on every backend (no TF32
    matmul), and no ``reduce`` of a broadcast product, which jaxlib 0.10.2's CPU compiler
    miscompiles once fused with a consumer (rows past ~2/3 of N >= 16384 read the wrong
    Gaussian; jax-ml/jax#39103)."""
    return jnp.stack(
        [vecs[:, 0] * rot[i, 0] + vecs[:, 1] * rot[i, 1] + vecs[:, 2] * rot[i, 2] for i in range(3)],
        axis=-1,
    )


def sanitise_inputs(
    means: Float[Array, "N 3"],
    quats: Float[Array, "N 4"],
    scales: Float[Array, "N S"],
    c2w: Float[Array, "4 4"],
    intrinsics: Float[Array, " 4"],
    keep: Bool[Array, " N"] | None = None,
) -> tuple[Bool[Array, " N"], Bool[Array, ""], Array, Array, Array, Array, Array]:
    """``(finite, camera_ok, means, quats, scales, c2w, intrinsics)``: which Gaussians have
    finite inputs (and ``keep``), whether the camera is valid, and the inputs with every
    dropped Gaussian's and an invalid camera's entries replaced by harmless values, so that
    they cannot produce NaN in gradients."""
    dtype = means.dtype
    finite = (
        jnp.all(jnp.isfinite(means), axis=-1)
        & jnp.all(jnp.isfinite(quats), axis=-1)
        & jnp.all(jnp.isfinite(scales), axis=-1)
    )
    if keep is not None:
        finite = finite & keep
    cam_ok = camera_is_valid(c2w, intrinsics)
    means = jnp.where(finite[:, None], means, 0.0)
    quats = jnp.where(finite[:, None], quats, jnp.asarray([1.0, 0.0, 0.0, 0.0], dtype)[None, :])
    scales = jnp.where(finite[:, None], scales, 0.0)
    c2w = jnp.where(cam_ok, c2w, jnp.eye(4, dtype=dtype))
    intrinsics = jnp.where(cam_ok, intrinsics, jnp.asarray([1.0, 1.0, 0.0, 0.0], dtype))
    return finite, cam_ok, means, quats, scales, c2w, intrinsics


def project_gaussians(
    means: Float[Array, "N 3"],
    quats: Float[Array, "N 4"],
    scales: Float[Array, "N 3"],
    c2w: Float[Array, "4 4"],
    intrinsics: Float[Array, " 4"],
    height: int,
    width: int,
    cfg: SplatConfig = SplatConfig(),
    keep: Bool[Array, " N"] | None = None,
) -> ProjectedGaussians:
    """Project N Gaussians (world space, linear ``scales``) onto an ``height x width`` canvas.

    Computes in ``means.dtype``; the other inputs must share it. ``keep`` (optional) culls
    Gaussians where False. See the module docstring for the exact rules.
    """
    finite, cam_ok, means, quats, scales, c2w, intrinsics = sanitise_inputs(means, quats, scales, c2w, intrinsics, keep)
    rot_w, trans_w = _world_to_camera(c2w)
    p = _rotate(rot_w, means) + trans_w[None, :]
    x, y, z = p[:, 0], p[:, 1], p[:, 2]
    fx, fy, cx, cy = intrinsics[0], intrinsics[1], intrinsics[2], intrinsics[3]

    in_range = (z > cfg.near) & (z < cfg.far)
    zs = jnp.where(in_range, z, 1.0)
    tan_fovx = 0.5 * width / fx
    tan_fovy = 0.5 * height / fy
    u = jnp.clip(x / zs, -(cx / fx + _FOV_MARGIN * tan_fovx), (width - cx) / fx + _FOV_MARGIN * tan_fovx)
    v = jnp.clip(y / zs, -(cy / fy + _FOV_MARGIN * tan_fovy), (height - cy) / fy + _FOV_MARGIN * tan_fovy)

    rs = quat_to_rotmat(quats) * scales[:, None, :]  # R diag(s), [N, 3, 3]
    wrs = jnp.stack([_rotate(rot_w, rs[:, :, k]) for k in range(3)], axis=-1)  # W R diag(s)
    m0 = (fx / zs)[:, None] * wrs[:, 0, :] - (fx * u / zs)[:, None] * wrs[:, 2, :]
    m1 = (fy / zs)[:, None] * wrs[:, 1, :] - (fy * v / zs)[:, None] * wrs[:, 2, :]

    bounded = jnp.all(jnp.abs(m0) < _MAX_FOOTPRINT, axis=-1) & jnp.all(jnp.abs(m1) < _MAX_FOOTPRINT, axis=-1)
    ok = finite & cam_ok & in_range & bounded
    m0 = jnp.where(ok[:, None], m0, 0.0)
    m1 = jnp.where(ok[:, None], m1, 0.0)

    eps = cfg.eps2d
    a0 = jnp.sum(m0 * m0, axis=-1)
    c0 = jnp.sum(m1 * m1, axis=-1)
    b = jnp.sum(m0 * m1, axis=-1)
    det0 = jnp.sum(jnp.square(_cross(m0, m1)), axis=-1)  # = a0 c0 - b^2 (Lagrange identity)
    a, c = a0 + eps, c0 + eps
    det = det0 + eps * (a0 + c0) + eps * eps
    ok = ok & (det > 0)
    det_safe = jnp.where(ok, det, 1.0)
    conics = jnp.stack([c / det_safe, -b / det_safe, a / det_safe], axis=-1)
    c_safe = jnp.where(ok, c, 1.0)  # det > 0 implies c > 0
    quad_form = jnp.stack([c / det_safe, -b / c_safe, 1.0 / c_safe], axis=-1)

    disc = jnp.square(0.5 * (a - c)) + b * b  # = ((a + c) / 2)^2 - det, without cancellation
    lam_max = 0.5 * (a + c) + jnp.sqrt(jnp.maximum(disc, 0.01))
    radius = jnp.ceil(cfg.radius_sigmas * jnp.sqrt(lam_max))
    radius = lax.stop_gradient(jnp.minimum(radius, _MAX_RADIUS))

    means2d = jnp.stack([fx * x / zs + cx, fy * y / zs + cy], axis=-1)
    inside = (
        (means2d[:, 0] + radius > 0)
        & (means2d[:, 0] - radius < width)
        & (means2d[:, 1] + radius > 0)
        & (means2d[:, 1] - radius < height)
    )
    visible = ok & inside
    return ProjectedGaussians(
        means2d=jnp.where(visible[:, None], means2d, 0.0),
        conics=jnp.where(visible[:, None], conics, 0.0),
        quad_form=jnp.where(visible[:, None], quad_form, 0.0),
        depths=jnp.where(visible, z, 0.0),
        radii=jnp.where(visible, radius, 0.0).astype(jnp.int32),
    )
