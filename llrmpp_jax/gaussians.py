"""The Gaussian head: backbone tokens -> a set of 3D Gaussians (feature or colour).

Feature mode (Long-LRM++, paper §3.2): each image token predicts K Gaussians through a
bias-free LayerNorm + linear. Per Gaussian, channels in this order:
``[feature F | offset 2 | distance 1 | quaternion 4 (wxyz) | opacity 1 | log-scale 3]``.
The centre is ``o + distance * d`` where ``d`` is the unit ray of the token's view through
the pixel position ``patch centre + offset``; ``offset = offset_scale * tanh(raw) * p``
pixels (default: within one patch of its own), or ``raw * p`` unbounded with
``offset_scale=None`` (the paper's offsets "move freely"; it gives no bound). The bounded
default cannot send a Gaussian off-screen early in training, and unbounding it made no
measurable difference (docs/lab-notes.md, "The Gaussians' offset bound").

Colour mode (Long-LRM, facts §1.6): the head predicts ``p_out**2`` Gaussians per token, one
per pixel, channels ``[xyz 3 | SH (deg+1)^2*3 | log-scale 3 | quaternion 4 | opacity 1]``;
the distance is ``sigmoid(mean(xyz_raw)) * max_dist`` along the pixel's own ray (centre
``+0.5``), SH coefficients are used raw (gsplat adds 0.5 when evaluating). With
``primitive="2dgs"`` (2D Gaussians, Long-LRM 2DGS) the log-scale group has two channels, the
surfel's two tangent scales: ``[xyz 3 | SH | log-scale 2 | quaternion 4 | opacity 1]``; the
normal is the rotation's third column (the splatter's rule), everything else is unchanged.

Activations (both modes, Long-LRM defaults): distance ``sigmoid(raw) * max_dist``,
log-scale ``min(raw + scale_bias, scale_max)`` (hard clamp, zero gradient above),
opacity ``sigmoid(raw + opacity_bias)``, quaternion normalised (a zero quaternion maps
to the identity rotation).
"""

from __future__ import annotations

import math
from typing import NamedTuple

import flax.linen as nn
import jax
import jax.numpy as jnp
import numpy as np
from flax.linen.dtypes import promote_dtype

from llrmpp_jax.array_typing import Array, ArrayLike, Float
from llrmpp_jax.config import GaussianHeadConfig
from llrmpp_jax.errors import UserError
from llrmpp_jax.nn.initializers import linear_init
from llrmpp_jax.nn.norms import LayerNorm

# Opacities are clipped to [eps, 1 - eps] before a logit (export, refinement): float32's
# sigmoid saturates to exactly 0 or 1, and 1 - 2^-24 is the largest float32 below 1.
OPACITY_LOGIT_EPS = 2.0**-24


class Gaussians(NamedTuple):
    """A batch of render-ready Gaussians (scene units, OpenCV world frame).

    ``features`` is ``[B, N, F]`` in feature mode and the flattened SH coefficients
    ``[B, N, (deg+1)^2 * 3]`` (coefficient-major, RGB fastest) in colour mode.
    """

    means: Float[Array, "B N 3"]
    quats: Float[Array, "B N 4"]  # unit, wxyz
    scales: Float[Array, "B N 3"] | Float[Array, "B N 2"]  # linear (exp of the clamped log-scale); 2 for 2DGS
    opacities: Float[Array, "B N"]  # in (0, 1)
    features: Float[Array, "B N F"]


# A 2D Gaussian stored where three scales are expected (a 3DGS PLY, for viewers that know only
# 3D Gaussians): its third axis, along the normal, is this fraction of its smaller tangent
# scale: a disk at any zoom a viewer reaches, and a covariance still invertible in float32
# (its smallest eigenvalue 1e-6 of the next).
SURFEL_THICKNESS = 1e-3


def surfel_scales_3d(scales: Float[ArrayLike, "*batch N 2"]) -> Float[np.ndarray, "*batch N 3"]:
    """2D Gaussians' tangent scales ``[..., N, 2]`` as three scales of flat 3D Gaussians: the
    third is :data:`SURFEL_THICKNESS` times the smaller tangent scale (the rotation's third
    column, the surfel's normal, is the thin axis). ``UserError`` unless the last axis is 2."""
    s = np.asarray(scales)
    if s.ndim < 2 or s.shape[-1] != 2:
        raise UserError(f"2D Gaussians' scales must be [..., N, 2], got shape {s.shape}")
    return np.concatenate([s, SURFEL_THICKNESS * np.min(s, axis=-1, keepdims=True)], axis=-1)


def _channels(cfg: GaussianHeadConfig) -> int:
    if cfg.mode == "color":
        return 3 + 3 * (cfg.sh_degree + 1) ** 2 + cfg.num_scales + 4 + 1
    return cfg.feature_dim + 2 + 1 + 4 + 1 + 3


def _feature_splits(f: int) -> list[int]:
    """Where a feature-mode Gaussian's channels split:
    ``[feature f | offset 2 | distance 1 | quaternion 4 | opacity 1 | log-scale 3]``."""
    return [f, f + 2, f + 3, f + 7, f + 8]


def gaussians_per_token(cfg: GaussianHeadConfig, token_stride: int) -> int:
    """K: Gaussians per token (one per pixel of the token's patch in colour mode)."""
    return token_stride**2 if cfg.mode == "color" else cfg.gaussians_per_token


def anchor_offsets(cfg: GaussianHeadConfig, token_stride: int) -> Float[Array, "K 2"]:
    """Feature mode: where each of a token's K Gaussians sits before its learned offset,
    ``(u, v)`` pixels from the patch's top-left corner: the patch centre for every k
    (``anchors="centre"``), or the centre of cell ``(k // m, k % m)`` of an ``m x m``
    sub-grid (``"grid"``, K = m*m)."""
    k, s = cfg.gaussians_per_token, token_stride
    if cfg.anchors == "centre":
        return jnp.full((k, 2), s / 2, jnp.float32)
    m = math.isqrt(k)
    cell = (jnp.arange(m, dtype=jnp.float32) + 0.5) * (s / m)
    return jnp.stack([jnp.tile(cell, m), jnp.repeat(cell, m)], axis=-1)


def head_kernel_init(cfg: GaussianHeadConfig, k: int) -> nn.initializers.Initializer:
    """The head's kernel ``[D, K * C]``: :func:`linear_init` of ``cfg.init_std``; with
    ``anchors="grid"`` the geometry columns (offset, distance, quaternion, log-scale) start at
    zero, so every Gaussian starts on its anchor, at ``max_dist / 2``, isotropic, of scale
    ``exp(scale_bias)``: the splatted canvas starts as a grid of the tokens' features."""
    base = linear_init(cfg.init_std)
    if cfg.mode == "color" or cfg.anchors == "centre":
        return base
    f, _, _, opacity, log_scale = _feature_splits(cfg.feature_dim)
    keep = jnp.ones((k, _channels(cfg)), jnp.float32).at[:, f:opacity].set(0.0).at[:, log_scale:].set(0.0)
    keep = keep.reshape(-1)

    def init(key, shape, dtype=jnp.float32):
        return base(key, shape, dtype) * keep.astype(dtype)[None, :]

    return init


def _unit_quat(q: Float[Array, "B 4 ..."]) -> Float[Array, "B 4 ..."]:
    """Normalise quaternions stored channel-major (axis 1); a zero one becomes the identity."""
    n2 = jnp.sum(jnp.square(q), axis=1, keepdims=True)
    ident = jnp.zeros_like(q).at[:, 0].set(1.0)
    safe = jnp.where(n2 > 1e-24, q, ident)
    return safe * jax.lax.rsqrt(jnp.sum(jnp.square(safe), axis=1, keepdims=True))


def decode_gaussians(
    raw: Float[ArrayLike, "B V h w K C"],
    c2w: Float[ArrayLike, "B V 4 4"],
    intrinsics: Float[ArrayLike, "B V 4"],
    token_stride: int,
    cfg: GaussianHeadConfig,
) -> Gaussians:
    """Turn raw head outputs into Gaussians (pure; the activations listed in the module doc).

    ``token_stride`` is the pixel size of one token (p, or p * 2^merges for Long-LRM).
    In colour mode ``K == token_stride**2``, Gaussian ``k`` of a token sits on pixel
    ``(k // token_stride, k % token_stride)`` of its patch, and the output is in pixel
    raster order (view, row, column); in feature mode the order is (view, token row,
    token column, k). :func:`decode_channel_major` with the channels moved to axis 1.
    """
    return decode_channel_major(jnp.moveaxis(jnp.asarray(raw), -1, 1), c2w, intrinsics, token_stride, cfg)


def decode_channel_major(
    raw: Float[ArrayLike, "B C V h w K"],
    c2w: Float[ArrayLike, "B V 4 4"],
    intrinsics: Float[ArrayLike, "B V 4"],
    token_stride: int,
    cfg: GaussianHeadConfig,
) -> Gaussians:
    """:func:`decode_gaussians` of raw outputs laid out channel-major, ``[B, C, V, h, w, K]``.

    Every channel group is a slice along axis 1 and every activation works on whole
    ``[B, V, h, w, K]`` planes; each field becomes ``[B, N, c]`` once, at the end. Why: the TPU
    compiler's code for slicing a 43-channel minor axis into groups of 1 to 32 grows with the
    image area (minutes at 32 views of 544x960); along a major axis the slices are free.
    """
    raw = jnp.asarray(raw)
    b, _, v, h, w, k = raw.shape
    s = token_stride
    # Patch top-left corners in pixels, shaped [1, 1, h, 1, 1] / [1, 1, 1, w, 1] to meet [B, V, h, w, K].
    rows = (jnp.arange(h, dtype=raw.dtype) * s).reshape(1, 1, h, 1, 1)
    cols = (jnp.arange(w, dtype=raw.dtype) * s).reshape(1, 1, 1, w, 1)
    if cfg.mode == "color":
        nsh = 3 * (cfg.sh_degree + 1) ** 2
        e = 3 + nsh + cfg.num_scales  # end of the log-scales (2 of them for 2D Gaussians)
        xyz, feat = raw[:, :3], raw[:, 3 : 3 + nsh]
        logs, quat, opac = raw[:, 3 + nsh : e], raw[:, e : e + 4], raw[:, e + 4 : e + 5]
        dist_raw = jnp.mean(xyz, axis=1)
        sub = jnp.arange(k, dtype=raw.dtype).reshape(1, 1, 1, 1, k)
        u = jnp.broadcast_to(cols + sub % s + 0.5, (b, v, h, w, k))  # pixel centres
        vv = jnp.broadcast_to(rows + sub // s + 0.5, (b, v, h, w, k))
    else:
        f = cfg.feature_dim
        feat, off, dist_raw = raw[:, :f], raw[:, f : f + 2], raw[:, f + 2]
        quat, opac, logs = raw[:, f + 3 : f + 7], raw[:, f + 7 : f + 8], raw[:, f + 8 : f + 11]
        off = s * off if cfg.offset_scale is None else cfg.offset_scale * s * jnp.tanh(off)
        anchor = anchor_offsets(cfg, s).astype(raw.dtype)  # [K, 2] pixels from the corner
        u = cols + anchor[:, 0].reshape(1, 1, 1, 1, k) + off[:, 0]
        vv = rows + anchor[:, 1].reshape(1, 1, 1, 1, k) + off[:, 1]
    origins, dirs = _rays(jnp.asarray(c2w, raw.dtype), jnp.asarray(intrinsics, raw.dtype), u, vv)
    dist = jax.nn.sigmoid(dist_raw) * cfg.max_dist
    means = jnp.stack([o + dist * d for o, d in zip(origins, dirs)], axis=1)
    log_scale = jnp.minimum(logs + cfg.scale_bias, cfg.scale_max)
    n = v * h * w * k

    def flat(a: Array) -> Array:  # [B, c, V, h, w, K] -> [B, N, c]
        c = a.shape[1]
        if cfg.mode == "color":  # pixel raster order (v, row, col), as Long-LRM's unpatchify
            a = a.reshape(b, c, v, h, w, s, s).transpose(0, 1, 2, 3, 5, 4, 6)
        return jnp.swapaxes(a.reshape(b, c, n), 1, 2)

    return Gaussians(
        means=flat(means),
        quats=flat(_unit_quat(quat)),
        scales=flat(jnp.exp(log_scale)),
        opacities=flat(jax.nn.sigmoid(opac + cfg.opacity_bias))[..., 0],
        features=flat(feat),
    )


def _rays(c2w: Array, intrinsics: Array, u: Array, v: Array) -> tuple[list[Array], list[Array]]:
    """Origins and unit directions, one ``[B, V, h, w, K]`` plane per axis, of the rays through
    pixel coordinates ``(u, v)`` of each view: :func:`llrmpp_jax.geometry.rays_through_pixels`
    computed per axis (``d = normalize(R @ [(u - cx) / fx, (v - cy) / fy, 1])``)."""
    per_view = lambda a: a[:, :, None, None, None]  # noqa: E731  [B, V] -> [B, V, 1, 1, 1]
    x = (u - per_view(intrinsics[..., 2])) / per_view(intrinsics[..., 0])
    y = (v - per_view(intrinsics[..., 3])) / per_view(intrinsics[..., 1])
    d = [per_view(c2w[..., i, 0]) * x + per_view(c2w[..., i, 1]) * y + per_view(c2w[..., i, 2]) for i in range(3)]
    norm = jnp.sqrt(d[0] * d[0] + d[1] * d[1] + d[2] * d[2])
    return [jnp.broadcast_to(per_view(c2w[..., i, 3]), u.shape) for i in range(3)], [di / norm for di in d]


class GaussianHead(nn.Module):
    """Bias-free LayerNorm + bias-free linear per token -> :func:`decode_gaussians`.

    Parameter names mirror Long-LRM's ``tokenDecoder`` (``norm`` = index 0, ``proj`` = 1).
    """

    cfg: GaussianHeadConfig
    token_stride: int

    @nn.compact
    def __call__(
        self,
        tokens: Float[ArrayLike, "B L D"],
        grid: tuple[int, int],
        c2w: Float[ArrayLike, "B V 4 4"],
        intrinsics: Float[ArrayLike, "B V 4"],
    ) -> Gaussians:
        b, length, d = tokens.shape
        h, w = grid
        v = c2w.shape[1]
        if length != v * h * w:
            raise ValueError(f"GaussianHead: {length} tokens != V*h*w = {v}*{h}*{w} from cameras and grid")
        k = gaussians_per_token(self.cfg, self.token_stride)
        x = LayerNorm(name="norm")(tokens)
        raw = _ChannelMajorLinear(k, _channels(self.cfg), head_kernel_init(self.cfg, k), name="proj")(x)
        # Geometry in float32 at least: bf16 tokens (bf16 compute) would put pixel
        # coordinates on a grid of 4 above 512 and ray depths to 3 digits.
        raw = raw.astype(jnp.float64 if raw.dtype == jnp.float64 else jnp.float32)
        return decode_channel_major(raw.reshape(b, -1, v, h, w, k), c2w, intrinsics, self.token_stride, self.cfg)


class _ChannelMajorLinear(nn.Module):
    """A bias-free linear layer ``[B, L, D] -> [B, C, L, K]``: ``nn.Dense(K * C)``'s parameter
    (``kernel [D, K * C]``, Gaussian-major, as Long-LRM's checkpoints hold it) and product, with
    the output laid out channel-major for :func:`decode_channel_major`."""

    k: int
    channels: int
    kernel_init: nn.initializers.Initializer

    @nn.compact
    def __call__(self, x: Float[ArrayLike, "B L D"]) -> Float[Array, "B C L K"]:
        kernel = self.param("kernel", self.kernel_init, (jnp.shape(x)[-1], self.k * self.channels), jnp.float32)
        x, kernel = promote_dtype(x, kernel, dtype=None)
        return jnp.einsum("bld,dkc->bclk", x, kernel.reshape(-1, self.k, self.channels))
