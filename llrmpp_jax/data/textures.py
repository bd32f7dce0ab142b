"""Texture bank for procedural scenes: scikit-image's bundled photographs (text, page,
brick, astronaut, ...) and generated patterns, each as a mip pyramid, plus a mip-mapped
bilinear lookup with wrap-around.

Fine detail is the point (readable text, sharp texture), so textures are used at their
native resolution; the mip level is picked per pixel from the pixel's footprint on the
surface so that far or small surfaces are filtered instead of aliasing.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass

import numpy as np
import skimage.data

from llrmpp_jax.array_typing import Float, Int

# Photographs shipped inside scikit-image (no download needed), by loader name.
_PHOTOS = (
    "text",
    "page",
    "brick",
    "astronaut",
    "checkerboard",
    "camera",
    "coffee",
    "chelsea",
    "grass",
    "gravel",
    "rocket",
    "coins",
    "moon",
    "hubble_deep_field",
    "immunohistochemistry",
    "clock",
)
# Textures that carry text or a single picture: shown once on a poster, never tiled.
POSTER_TEXTURES = (
    "text",
    "page",
    "astronaut",
    "camera",
    "coffee",
    "chelsea",
    "rocket",
    "coins",
    "clock",
    "hubble_deep_field",
    "checkerboard",
)
_PATTERN_SIZE = 256


@dataclass(frozen=True)
class Texture:
    """One texture: ``levels[0]`` is ``[h, w, 3]`` float32 in [0, 1], each next level half
    the size (down to a few texels); ``grey`` marks single-channel sources (tinted at use)."""

    name: str
    levels: tuple[np.ndarray, ...]
    grey: bool


def _photo(name: str) -> tuple[np.ndarray, bool]:
    img = np.asarray(getattr(skimage.data, name)())
    grey = img.ndim == 2
    img = img.astype(np.float32) / (255.0 if img.dtype != np.bool_ else 1.0)
    if grey:
        img = np.repeat(img[:, :, None], 3, axis=2)
    return np.ascontiguousarray(img[:, :, :3]), grey


def _patterns() -> list[tuple[str, np.ndarray, bool]]:
    """Generated patterns with sharp edges and fine periodic detail (fixed seed)."""
    n = _PATTERN_SIZE
    y, x = np.meshgrid(np.arange(n) + 0.5, np.arange(n) + 0.5, indexing="ij")
    rng = np.random.default_rng(1234)
    out = []
    checks = ((x // 16 + y // 16) % 2).astype(np.float32)
    out.append(("checker_fine", checks, True))
    stripes = (np.sin(2 * np.pi * x / 12.0) > 0).astype(np.float32) * 0.8 + 0.1
    out.append(("stripes", stripes, True))
    grid = np.where((x % 32 < 2) | (y % 32 < 2), 0.15, 0.85).astype(np.float32)
    out.append(("tiles", grid, True))
    dots = (((x % 24) - 12) ** 2 + ((y % 24) - 12) ** 2 < 36).astype(np.float32) * 0.7 + 0.2
    out.append(("dots", dots, True))
    # Smooth periodic colour noise: random phases under a 1/f^1.6 amplitude spectrum.
    freq = np.hypot(np.fft.fftfreq(n)[:, None], np.fft.rfftfreq(n)[None, :]) * n
    amp = np.where(freq > 0, np.maximum(freq, 1.0) ** -1.6, 0.0)
    spectrum = amp[:, :, None] * np.exp(2j * np.pi * rng.random((n, n // 2 + 1, 3)))
    noise = np.fft.irfft2(spectrum, s=(n, n), axes=(0, 1)).astype(np.float32)
    out.append(("value_noise", (noise - noise.min()) / (noise.max() - noise.min()), False))
    rings = 0.5 + 0.5 * np.cos(np.hypot(x - n / 2, y - n / 2) / 3.0)
    out.append(("rings", rings.astype(np.float32), True))
    return [(name, img if img.ndim == 3 else np.repeat(img[:, :, None], 3, axis=2), grey) for name, img, grey in out]


def _pyramid(img: np.ndarray) -> tuple[np.ndarray, ...]:
    """2x2 box-filtered levels; an odd last row/column is dropped (under one texel of drift)."""
    levels = [img]
    while min(levels[-1].shape[:2]) >= 8:
        h, w = (s // 2 for s in levels[-1].shape[:2])
        levels.append(levels[-1][: 2 * h, : 2 * w].reshape(h, 2, w, 2, 3).mean(axis=(1, 3)))
    return tuple(np.ascontiguousarray(lv, dtype=np.float32) for lv in levels)


@functools.lru_cache(maxsize=1)
def texture_bank() -> tuple[Texture, ...]:
    """All textures, in a fixed order (so a seed always picks the same ones)."""
    items = [(name, *_photo(name)) for name in _PHOTOS] + _patterns()
    return tuple(Texture(name, _pyramid(img), grey) for name, img, grey in items)


def texture_index(name: str) -> int:
    """Position of texture ``name`` in :func:`texture_bank`."""
    names = [t.name for t in texture_bank()]
    if name not in names:
        raise ValueError(f"unknown texture {name!r}; available: {names}")
    return names.index(name)


def _bilinear_wrap(tex: np.ndarray, u: np.ndarray, v: np.ndarray) -> np.ndarray:
    h, w = tex.shape[:2]
    x = u * w - 0.5
    y = v * h - 0.5
    x0 = np.floor(x)
    y0 = np.floor(y)
    fx = (x - x0)[:, None]
    fy = (y - y0)[:, None]
    x0 = x0.astype(np.int64) % w
    y0 = y0.astype(np.int64) % h
    x1 = (x0 + 1) % w
    y1 = (y0 + 1) % h
    top = tex[y0, x0] * (1 - fx) + tex[y0, x1] * fx
    bottom = tex[y1, x0] * (1 - fx) + tex[y1, x1] * fx
    return top * (1 - fy) + bottom * fy


def sample_texture(
    texture: Texture, u: Float[np.ndarray, " pts"], v: Float[np.ndarray, " pts"], lod: Float[np.ndarray, " pts"]
) -> Float[np.ndarray, "pts 3"]:
    """Bilinear lookup with wrap-around at texture coordinates ``(u, v)`` (1 = one full
    texture; v grows downwards) from mip level ``round(lod)`` (clamped to the pyramid)."""
    level = np.clip(np.rint(lod), 0, len(texture.levels) - 1).astype(np.int64)
    out = np.empty((u.shape[0], 3), dtype=np.float32)
    for lv in np.unique(level):
        sel = level == lv
        out[sel] = _bilinear_wrap(texture.levels[lv], u[sel], v[sel])
    return out


def texture_ids(names: tuple[str, ...]) -> Int[np.ndarray, " textures"]:
    """Indices of several textures in the bank."""
    return np.array([texture_index(n) for n in names], dtype=np.int64)
