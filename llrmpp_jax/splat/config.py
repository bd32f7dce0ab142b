"""Static settings of the feature splatter.

Every field is a Python number, so a ``SplatConfig`` is hashable and can be a static
argument of ``jax.jit``. Defaults follow gsplat's ``rasterize_mode="classic"`` as called by
Long-LRM (tile 16, ``eps2d`` 0.3, near 0.01, far 1e6, alpha in ``[1/255, 0.999]``, stop at
transmittance ``<= 1e-4``) and gsplat v1.4's isotropic 3-sigma screen radius.

Tiles
-----
``tile_size`` (16) is gsplat's rule of which Gaussians a pixel sees: a Gaussian is drawn
on the 16x16 tiles its screen box (``[mean - r, mean + r]``, ``r = ceil(3 sqrt(lambda_max))``
pixels) touches. The compositor works on smaller blocks of ``composite_tile`` pixels (8):
each block's list holds the Gaussians of its 16x16 tile that can reach the block at all
(:func:`~llrmpp_jax.splat.binning.screen_extents`), so every pixel composites exactly the
entries it would with 16x16 lists, and a block of 64 pixels evaluates far fewer
(Gaussian, pixel) pairs than a tile of 256 (docs/speed-cpu.md, "The splatter").

Sizing the intersection buffer
------------------------------
Every visible Gaussian writes one entry per compositor block it reaches, so the buffer
needs ``sum_visible blocks(g)`` slots. This number depends on the scene, not only on N, and
JAX needs it as a static shape, so it is a capacity:

* ``max_intersections`` (an int) fixes the buffer size; ``None`` derives it at trace time
  as ``ceil(intersections_per_gaussian * N)`` (at least one slot per block, at most
  ``N * blocks``, which can never overflow): :meth:`SplatConfig.capacity`. Called
  outside ``jit`` with concrete arrays, :func:`~llrmpp_jax.splat.rasterize` sizes it from
  the scene itself instead (:func:`~llrmpp_jax.splat.fit_capacity`).
* A Gaussian of screen footprint sigma (pixels) touches about ``(1 + 6 sigma / 8)^2``
  blocks. Long-LRM++ at its paper config predicts ~4.2M Gaussians whose footprint is about
  one canvas pixel (16 Gaussians per 8x8-pixel token rendered at half resolution), i.e.
  2-4 blocks each, and not all of them are in a target's frustum. The default of
  8 slots per Gaussian leaves a 2x margin there (tested at that density in
  ``tests/splat/test_binning.py``); colour mode (one Gaussian per pixel) is similar.
* :func:`llrmpp_jax.splat.fit_capacity` sets ``max_intersections`` from the cameras a
  scene will be rendered at (with a ``headroom`` factor for Gaussians that still move, as
  in refinement); :func:`llrmpp_jax.model.fit_capacity` does it for a model's render.
  Every render also reports ``stats.num_intersections`` and ``stats.overflow``. Memory is about 12 bytes
  per slot plus the sort's scratch, per rendered camera.
* On overflow the buffer keeps the intersections of the nearest Gaussians (entries are
  emitted in depth order) and drops the farthest ones; ``stats.overflow`` is set and
  ``stats.num_dropped`` counts the lost entries. Nothing is dropped silently.

Loop shape (speed only, results do not depend on it): blocks are sorted by occupancy and
processed in groups of ``tiles_per_group``; each group runs a dynamic loop over chunks of
``chunk_size`` Gaussians until its busiest block is exhausted or all its pixels are
saturated, so the cost follows the real work, not a static per-block bound.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from llrmpp_jax.errors import UserError


@dataclass(frozen=True)
class SplatConfig:
    """Splatter settings; see the module docstring for how to size the capacity."""

    tile_size: int = 16  # gsplat's tile: a Gaussian is drawn on the 16x16 tiles its box touches
    composite_tile: int = 8  # the compositor's block of pixels (divides tile_size; speed only)
    eps2d: float = 0.3  # screen-space dilation added to the 2D covariance (pixels^2)
    near: float = 0.01  # camera-space z range kept (scene units)
    far: float = 1e6
    radius_sigmas: float = 3.0  # screen radius = ceil(radius_sigmas * sqrt(lambda_max))
    alpha_min: float = 1.0 / 255.0  # contributions with alpha below this are skipped
    alpha_max: float = 0.999  # alpha is clamped to this
    t_min: float = 1e-4  # a pixel stops before transmittance would fall to <= t_min
    max_intersections: int | None = None  # static buffer size; None: derived from N
    intersections_per_gaussian: float = 8.0  # used when max_intersections is None
    chunk_size: int = 64  # Gaussians per tile per loop step
    tiles_per_group: int = 64  # tiles advanced together by one dynamic loop

    def __post_init__(self) -> None:
        for name in ("tile_size", "composite_tile", "chunk_size", "tiles_per_group"):
            if int(getattr(self, name)) < 1:
                raise UserError(f"SplatConfig.{name} must be >= 1, got {getattr(self, name)}")
        if self.tile_size % self.composite_tile:
            raise UserError(
                f"SplatConfig.composite_tile must divide tile_size, got composite_tile="
                f"{self.composite_tile}, tile_size={self.tile_size}"
            )
        if not 0.0 < self.near < self.far:
            raise UserError(f"SplatConfig: need 0 < near < far, got near={self.near}, far={self.far}")
        if not 0.0 < self.alpha_min <= self.alpha_max < 1.0:
            raise UserError(
                "SplatConfig: need 0 < alpha_min <= alpha_max < 1, got "
                f"alpha_min={self.alpha_min}, alpha_max={self.alpha_max}"
            )
        if not 0.0 <= self.t_min < 1.0:
            raise UserError(f"SplatConfig.t_min must be in [0, 1), got {self.t_min}")
        if self.eps2d < 0.0 or self.radius_sigmas <= 0.0:
            raise UserError(
                f"SplatConfig: need eps2d >= 0 and radius_sigmas > 0, got eps2d={self.eps2d}, "
                f"radius_sigmas={self.radius_sigmas}"
            )
        if self.max_intersections is not None and not 1 <= self.max_intersections < 2**30:
            raise UserError(f"SplatConfig.max_intersections must be in [1, 2**30), got {self.max_intersections}")
        if self.intersections_per_gaussian <= 0.0:
            raise UserError(
                f"SplatConfig.intersections_per_gaussian must be > 0, got {self.intersections_per_gaussian}"
            )

    def tile_grid(self, height: int, width: int) -> tuple[int, int]:
        """Number of compositor tiles ``(tiles_y, tiles_x)`` (``composite_tile`` pixels a
        side) covering an ``height x width`` canvas."""
        return -(-height // self.composite_tile), -(-width // self.composite_tile)

    def capacity(self, num_gaussians: int, height: int, width: int) -> int:
        """Static intersection-buffer size (``(Gaussian, compositor tile)`` slots) for N
        Gaussians on an ``height x width`` canvas."""
        tiles_y, tiles_x = self.tile_grid(height, width)
        most = max(num_gaussians * tiles_y * tiles_x, 1)
        if self.max_intersections is not None:
            return min(self.max_intersections, most)
        derived = math.ceil(self.intersections_per_gaussian * num_gaussians)
        return min(max(derived, tiles_y * tiles_x), most, 2**30 - 1)
