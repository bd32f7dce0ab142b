"""Real spherical harmonics (degree 0-3) with gsplat's constants and coefficient order.

Coefficient ``k = l^2 + l + m`` multiplies the real SH basis of degree l, order m, in the
convention ``Y_{l,m} = sqrt(2) Re Y_l^m`` (m > 0), ``sqrt(2) Im Y_l^|m|`` (m < 0),
``Y_l^0`` (m = 0), with the complex ``Y_l^m`` including the Condon-Shortley phase
(the 3DGS / gsplat basis: ``Y_1 = (-C1 y, C1 z, -C1 x)``). Long-LRM's colour Gaussians
use degree 3 (16 coefficients per colour channel) and gsplat's ``max(sh + 0.5, 0)``.
"""

from __future__ import annotations

import jax.numpy as jnp
from jax import lax

from llrmpp_jax.array_typing import Array, Float

MAX_DEGREE = 3
SH_C0 = 0.2820947917738781  # Y_0^0: colour = SH_C0 x DC coefficient + 0.5 for a view-independent colour
_DIR_EPS = 1e-12  # gsplat's F.normalize eps


def num_sh_bases(degree: int) -> int:
    """``(degree + 1)^2`` coefficients per channel."""
    return (degree + 1) ** 2


def sh_basis(dirs: Float[Array, "N 3"], degree: int) -> Float[Array, "N bases"]:
    """Real SH basis ``[N, (degree+1)^2]`` at unit directions ``dirs``."""
    if not 0 <= degree <= MAX_DEGREE:
        raise ValueError(f"sh_basis: degree must be in [0, {MAX_DEGREE}], got {degree}")
    x, y, z = dirs[:, 0], dirs[:, 1], dirs[:, 2]
    out = [jnp.full_like(x, SH_C0)]
    if degree >= 1:
        out += [-0.48860251190292 * y, 0.48860251190292 * z, -0.48860251190292 * x]
    if degree >= 2:
        z2 = z * z
        c1, s1 = x * x - y * y, 2.0 * x * y
        out += [
            0.5462742152960395 * s1,
            -1.092548430592079 * z * y,
            0.9461746957575601 * z2 - 0.3153915652525201,
            -1.092548430592079 * z * x,
            0.5462742152960395 * c1,
        ]
    if degree >= 3:
        c2, s2 = x * c1 - y * s1, x * s1 + y * c1
        tmp_c = -2.285228997322329 * z2 + 0.4570457994644658
        tmp_b = 1.445305721320277 * z
        out += [
            -0.5900435899266435 * s2,
            tmp_b * s1,
            tmp_c * y,
            z * (1.865881662950577 * z2 - 1.119528997770346),
            tmp_c * x,
            tmp_b * c1,
            -0.5900435899266435 * c2,
        ]
    return jnp.stack(out, axis=-1)


def eval_sh(dirs: Float[Array, "N 3"], coeffs: Float[Array, "N sh 3"], degree: int) -> Float[Array, "N 3"]:
    """``sum_k Y_k(dir / |dir|) coeffs[:, k]`` over the first ``(degree+1)^2`` coefficients.

    ``dirs`` need not be unit length; a zero direction gives only the degree-0 term.
    """
    nb = num_sh_bases(degree)
    if coeffs.shape[1] < nb:
        raise ValueError(f"eval_sh: degree {degree} needs {nb} coefficients, sh_coeffs has shape {coeffs.shape}")
    sq = jnp.sum(dirs * dirs, axis=-1, keepdims=True)
    unit = dirs * lax.rsqrt(jnp.maximum(sq, _DIR_EPS**2))
    basis = sh_basis(unit, degree)
    # Elementwise multiply-sum: exact float32 on every backend (no TF32 matmul).
    return jnp.sum(basis[:, :, None] * coeffs[:, :nb, :], axis=1)


def sh_colors(
    means: Float[Array, "N 3"],
    sh_coeffs: Float[Array, "N sh 3"],
    c2w: Float[Array, "4 4"],
    degree: int,
) -> Float[Array, "N 3"]:
    """gsplat colour of each Gaussian seen from the camera centre: ``max(SH(mean - o) + 0.5, 0)``."""
    dirs = means - c2w[:3, 3][None, :]
    return jnp.maximum(eval_sh(dirs, sh_coeffs, degree) + 0.5, 0.0)
