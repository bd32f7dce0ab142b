"""OpenCV radial-tangential lens distortion ``(k1, k2, p1, p2, k3)``.

On normalised coordinates ``(x, y) = ((u - cx) / fx, (v - cy) / fy)`` with ``r^2 = x^2 + y^2``:
``x_d = x (1 + k1 r^2 + k2 r^4 + k3 r^6) + 2 p1 x y + p2 (r^2 + 2 x^2)`` and
``y_d = y (1 + k1 r^2 + k2 r^4 + k3 r^6) + p1 (r^2 + 2 y^2) + 2 p2 x y``.
COLMAP's SIMPLE_RADIAL / RADIAL / OPENCV and nerfstudio's OPENCV models are special cases.

Undistorted images keep the same pinhole intrinsics (no new camera matrix): each output
pixel centre is pushed through the distortion and the input sampled there; samples that
fall outside the input take the nearest border value.
"""

from __future__ import annotations

import functools

import numpy as np

from llrmpp_jax.array_typing import Float
from llrmpp_jax.data.resample import remap


def _check_coeffs(coeffs: np.ndarray) -> np.ndarray:
    coeffs = np.asarray(coeffs, dtype=np.float64)
    if coeffs.shape != (5,):
        raise ValueError(f"distortion: expected 5 coefficients (k1, k2, p1, p2, k3), got shape {coeffs.shape}")
    return coeffs


def distort_normalized(xy: Float[np.ndarray, "... 2"], coeffs: Float[np.ndarray, " 5"]) -> Float[np.ndarray, "... 2"]:
    """Apply the distortion to normalised coordinates ``[..., 2]``."""
    k1, k2, p1, p2, k3 = _check_coeffs(coeffs)
    x, y = xy[..., 0], xy[..., 1]
    r2 = x * x + y * y
    radial = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))
    xd = x * radial + 2.0 * p1 * x * y + p2 * (r2 + 2.0 * x * x)
    yd = y * radial + p1 * (r2 + 2.0 * y * y) + 2.0 * p2 * x * y
    return np.stack([xd, yd], axis=-1)


def distort_pixels(
    pixels: Float[np.ndarray, "... 2"], intrinsics: Float[np.ndarray, " 4"], coeffs: Float[np.ndarray, " 5"]
) -> Float[np.ndarray, "... 2"]:
    """Ideal pinhole pixel coordinates -> where the real (distorted) lens images them."""
    fx, fy, cx, cy = np.asarray(intrinsics, dtype=np.float64)
    f, c = np.array([fx, fy]), np.array([cx, cy])
    return distort_normalized((np.asarray(pixels, dtype=np.float64) - c) / f, coeffs) * f + c


def undistort_pixels(
    pixels: Float[np.ndarray, "... 2"],
    intrinsics: Float[np.ndarray, " 4"],
    coeffs: Float[np.ndarray, " 5"],
    iterations: int = 20,
) -> Float[np.ndarray, "... 2"]:
    """Distorted pixel coordinates (e.g. COLMAP observations) -> ideal pinhole coordinates,
    by fixed-point iteration of :func:`distort_normalized` (OpenCV's method)."""
    fx, fy, cx, cy = np.asarray(intrinsics, dtype=np.float64)
    f, c = np.array([fx, fy]), np.array([cx, cy])
    target = (np.asarray(pixels, dtype=np.float64) - c) / f
    xy = target
    for _ in range(iterations):
        xy = xy + (target - distort_normalized(xy, coeffs))
    return xy * f + c


@functools.lru_cache(maxsize=64)
def _source_grid(intr: tuple[float, ...], coeffs: tuple[float, ...], height: int, width: int) -> np.ndarray:
    x = np.arange(width, dtype=np.float64) + 0.5
    y = np.arange(height, dtype=np.float64) + 0.5
    grid = np.stack(np.meshgrid(x, y, indexing="xy"), axis=-1)
    return distort_pixels(grid, np.array(intr), np.array(coeffs)).astype(np.float32)


def undistort_image(
    image: Float[np.ndarray, "H W ..."],
    intrinsics: Float[np.ndarray, " 4"],
    coeffs: Float[np.ndarray, " 5"],
    nearest: bool = False,
) -> Float[np.ndarray, "H W ..."]:
    """Resample a distorted image (``[H, W, C]`` colour, bilinear; or ``[H, W]`` depth with
    ``nearest``) into the ideal pinhole camera with the same ``intrinsics``."""
    coeffs = _check_coeffs(coeffs)
    if not coeffs.any():
        return image
    h, w = image.shape[:2]
    grid = _source_grid(tuple(np.asarray(intrinsics, dtype=np.float64).tolist()), tuple(coeffs.tolist()), h, w)
    return remap(image, grid, nearest=nearest).astype(image.dtype)
