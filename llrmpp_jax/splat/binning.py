"""Tile binning: (tile, depth)-sorted Gaussian lists in a static-capacity buffer.

Each visible Gaussian intersects the tiles of its screen box, gsplat's rule:
``x in [floor(mx/ts - r/ts), ceil(mx/ts + r/ts))`` (same for y), clipped to the grid.
Given the opacities, the box shrinks to where the Gaussian can be drawn at all
(:func:`screen_extents`); what is rendered does not change, only the work.
Steps, all O(N + C) apart from two sorts, no 64-bit keys:

1. sort the Gaussians by depth (stable: ties keep index order), culled ones last;
2. a prefix sum of their tile counts (saturating for huge problems) gives each
   Gaussian its first slot;
3. every slot finds its Gaussian by a scatter-max of the start slots and a running max
   (no per-slot search), then its tile from the slot's rank inside the Gaussian's box;
4. one stable sort of the slots by tile id; since slots were emitted in depth order, each
   tile's list comes out depth-sorted;
5. per-tile ranges by a binary search of every tile id in the sorted keys.

Slots beyond the needed count hold a sentinel tile and are ignored. If more slots are
needed than the capacity, the nearest Gaussians keep theirs; ``overflow`` and
``num_dropped`` say so (see :mod:`llrmpp_jax.splat.config`).
"""

from __future__ import annotations

from typing import NamedTuple

import jax.numpy as jnp
from jax import lax

from llrmpp_jax.array_typing import Array, Bool, Float, Int
from llrmpp_jax.splat.config import SplatConfig
from llrmpp_jax.splat.projection import ProjectedGaussians

# Prefix sums of intersection counts saturate here, so int32 never wraps.
SATURATION = 2**30 - 1


class TileBins(NamedTuple):
    """Depth-sorted Gaussian lists of all tiles (row-major, ``tiles = tiles_y * tiles_x``;
    ``isect`` = buffer capacity)."""

    gaussian_ids: Int[Array, "isect"]  # Gaussian index of each slot, grouped by tile
    tile_start: Int[Array, "tiles"]  # first slot of each tile
    tile_count: Int[Array, "tiles"]  # number of slots of each tile
    num_intersections: Int[Array, ""]  # slots needed (exact below 2**30)
    overflow: Bool[Array, ""]  # needed > capacity: the farthest entries were dropped
    num_dropped: Int[Array, ""]  # max(needed - capacity, 0)


def screen_extents(
    projected: ProjectedGaussians, cfg: SplatConfig, opacities: Float[Array, "N"] | None = None
) -> tuple[Float[Array, "N"], Float[Array, "N"]]:
    """Half-widths ``(ex, ey)`` in pixels of each Gaussian's screen box.

    Without ``opacities``: the screen radius on both axes (gsplat v1.4's 3-sigma square).
    With them, each axis is capped where the Gaussian can still pass the compositor's
    ``alpha >= alpha_min`` test: ``o exp(-sigma) >= alpha_min`` needs
    ``sigma <= L = ln(o / alpha_min)``, and on that ellipse ``|dx| <= sqrt(2 L Sigma_xx)``
    (``Sigma = conic^-1``, so ``Sigma_xx = c / det``, ``Sigma_yy = a / det``). A tile
    outside this box holds no pixel the Gaussian is drawn on, so dropping it leaves every
    output and gradient as it was (gsplat's optional opacity-tightened boxes, its PR #597,
    rest on the same bound); ``L`` gets a slack of 0.01 (alpha within 1%) against rounding. A
    Gaussian with ``o < alpha_min`` gets an empty box. Feature Gaussians are mostly faint
    (median opacity 0.11 for the untrained cpu-scale model of ``notebooks/``): their
    (Gaussian, tile) pairs drop by 37% on a 64x64 canvas and 26% on 32x32, and by 14-18%
    for ``experiments/bench_splat.py``'s opacities in [0.05, 0.5].
    """
    r = projected.radii.astype(projected.means2d.dtype)
    if opacities is None:
        return r, r
    # Binning is not differentiated: cut the graph at the inputs (no sqrt(0) tangents).
    conics, opacities = lax.stop_gradient(projected.conics), lax.stop_gradient(opacities)
    a, b, c = conics[:, 0], conics[:, 1], conics[:, 2]
    det = a * c - b * b
    ok = (projected.radii > 0) & (det > 0)
    det = jnp.where(ok, det, 1.0)
    level = jnp.log(jnp.maximum(opacities.astype(r.dtype), 1e-30) / cfg.alpha_min) + 0.01
    two_l = jnp.where(ok, 2.0 * jnp.maximum(level, 0.0), 0.0)
    ex = jnp.minimum(r, jnp.sqrt(two_l * jnp.maximum(c, 0.0) / det))
    ey = jnp.minimum(r, jnp.sqrt(two_l * jnp.maximum(a, 0.0) / det))
    return ex, ey


def tile_rects(
    projected: ProjectedGaussians, height: int, width: int, cfg: SplatConfig,
    opacities: Float[Array, "N"] | None = None,
) -> tuple[Int[Array, "N"], Int[Array, "N"], Int[Array, "N"], Int[Array, "N"]]:
    """Half-open tile box ``(x0, x1, y0, y1)`` of each Gaussian; empty when culled or, given
    ``opacities``, when it is too faint to be drawn (:func:`screen_extents`)."""
    tiles_y, tiles_x = cfg.tile_grid(height, width)
    ts = float(cfg.tile_size)
    ex, ey = screen_extents(projected, cfg, opacities)
    tx = projected.means2d[:, 0] / ts
    ty = projected.means2d[:, 1] / ts
    x0 = jnp.clip(jnp.floor(tx - ex / ts), 0, tiles_x).astype(jnp.int32)
    x1 = jnp.clip(jnp.ceil(tx + ex / ts), 0, tiles_x).astype(jnp.int32)
    y0 = jnp.clip(jnp.floor(ty - ey / ts), 0, tiles_y).astype(jnp.int32)
    y1 = jnp.clip(jnp.ceil(ty + ey / ts), 0, tiles_y).astype(jnp.int32)
    drawn = (ex > 0) & (ey > 0)  # culled Gaussians have radius 0, so extent 0
    return x0, jnp.where(drawn, x1, x0), y0, jnp.where(drawn, y1, y0)


def intersection_counts(
    projected: ProjectedGaussians, height: int, width: int, cfg: SplatConfig
) -> Int[Array, "N"]:
    """Number of tiles each Gaussian's untrimmed box intersects (0 when culled)."""
    x0, x1, y0, y1 = tile_rects(projected, height, width, cfg)
    return (x1 - x0) * (y1 - y0)


def _saturating_add(a: Int[Array, "..."], b: Int[Array, "..."]) -> Int[Array, "..."]:
    return jnp.minimum(a + b, SATURATION)


def _inclusive_prefix_sum(counts: Int[Array, "N"], num_tiles: int) -> Int[Array, "N"]:
    """Running total of intersection counts, saturating at ``SATURATION``.

    Each count is at most ``num_tiles``, so a plain int32 cumsum is exact whenever
    ``N * num_tiles < 2**31`` (static); only larger problems pay for the saturating scan.
    """
    if counts.shape[0] * num_tiles < 2**31:
        return jnp.cumsum(counts, dtype=jnp.int32)
    return lax.associative_scan(_saturating_add, counts)


def bin_gaussians(
    projected: ProjectedGaussians, height: int, width: int, capacity: int, cfg: SplatConfig,
    opacities: Float[Array, "N"] | None = None,
) -> TileBins:
    """Bin projected Gaussians into depth-sorted per-tile lists of ``capacity`` slots.

    ``opacities`` (the largest of any copy that will be composited from these bins) trims
    each box to where the Gaussian can be drawn (:func:`screen_extents`)."""
    n = projected.radii.shape[0]
    tiles_y, tiles_x = cfg.tile_grid(height, width)
    num_tiles = tiles_y * tiles_x
    x0, x1, y0, y1 = tile_rects(projected, height, width, cfg, opacities)
    counts = (x1 - x0) * (y1 - y0)

    depth_key = jnp.where(counts > 0, projected.depths, jnp.inf)
    order = jnp.argsort(depth_key, stable=True).astype(jnp.int32)
    counts_sorted = counts[order]
    ends = _inclusive_prefix_sum(counts_sorted, num_tiles)
    starts = jnp.concatenate([jnp.zeros((1,), jnp.int32), ends[:-1]])
    needed = ends[-1]

    # Slot -> position in depth order: mark each start, then carry the mark forward.
    # Empty Gaussians share their start with the next non-empty one, which has the larger
    # position and so wins the max.
    slots = jnp.arange(capacity, dtype=jnp.int32)
    src = jnp.zeros((capacity,), jnp.int32).at[starts].max(jnp.arange(n, dtype=jnp.int32), mode="drop")
    src = lax.cummax(src)
    gid = order[src]
    rank = slots - starts[src]
    box_w = jnp.maximum(x1 - x0, 1)[gid]
    tile = (y0[gid] + rank // box_w) * tiles_x + x0[gid] + rank % box_w
    tile = jnp.where(slots < needed, tile, num_tiles)  # sentinel sorts after every tile

    sorted_tile, sorted_gid = lax.sort((tile, gid), num_keys=1, is_stable=True)
    bounds = jnp.searchsorted(sorted_tile, jnp.arange(num_tiles + 1, dtype=jnp.int32), side="left")
    bounds = bounds.astype(jnp.int32)
    return TileBins(
        gaussian_ids=sorted_gid,
        tile_start=bounds[:-1],
        tile_count=bounds[1:] - bounds[:-1],
        num_intersections=needed,
        overflow=needed > capacity,
        num_dropped=jnp.maximum(needed - capacity, 0),
    )
