"""Tile binning: (block, depth)-sorted Gaussian lists in a static-capacity buffer.

Each visible Gaussian is drawn on the 16x16 tiles of its screen box, gsplat's rule:
``x in [floor(mx/ts - r/ts), ceil(mx/ts + r/ts))`` (same for y). The compositor works on
blocks of ``cfg.composite_tile`` pixels; a Gaussian enters the lists of the blocks inside
its tiles that it can reach at all given its opacity (:func:`screen_extents`), so each
pixel meets exactly the entries it would meet in its 16x16 tile's list, minus entries that
are below ``alpha_min`` there and would be skipped anyway. Steps, all O(N + C) apart from
two sorts:

1. sort the Gaussians by depth (stable: ties keep index order), culled ones last
   (:func:`depth_order`: one int32 key sort);
2. a prefix sum of their block counts (saturating for huge problems) gives each
   Gaussian its first slot;
3. every slot finds its Gaussian by a scatter-max of the start slots and a running max
   (no per-slot search), then its block from the slot's rank inside the Gaussian's box;
   given opacities, a block the Gaussian's ``alpha >= alpha_min`` ellipse misses gets the
   sentinel instead (:func:`_reaches_block`), so the slot is sorted out of every list;
4. one sort of the slots by (block, depth rank), so each block's list comes out
   depth-sorted. When ``(blocks + 1) x N < 2**31`` (static) the pair is packed into one
   int32 key, whose sort is faster than sorting two arrays on CPU; otherwise a stable
   sort by block of slots emitted in depth order;
5. per-block ranges by a binary search of every block id in the sorted keys.

Slots beyond the needed count hold a sentinel block and are ignored. If more slots are
needed than the capacity, the nearest Gaussians keep theirs; ``overflow`` and
``num_dropped`` say so (see :mod:`llrmpp_jax.splat.config`).
"""

from __future__ import annotations

from typing import NamedTuple

import jax
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

    gaussian_ids: Int[Array, " isect"]  # Gaussian index of each slot, grouped by tile
    tile_start: Int[Array, " tiles"]  # first slot of each tile
    tile_count: Int[Array, " tiles"]  # number of slots of each tile
    num_intersections: Int[Array, ""]  # slots needed (exact below 2**30)
    overflow: Bool[Array, ""]  # needed > capacity: the farthest entries were dropped
    num_dropped: Int[Array, ""]  # max(needed - capacity, 0)


def screen_extents(
    projected: ProjectedGaussians, cfg: SplatConfig, opacities: Float[Array, " N"] | None = None
) -> tuple[Float[Array, " N"], Float[Array, " N"]]:
    """Half-widths ``(ex, ey)`` in pixels of the box where each Gaussian can be drawn.

    Without ``opacities``: unbounded (``inf``; the tile rule alone decides). With them,
    each axis is capped where the Gaussian can still pass the compositor's
    ``alpha >= alpha_min`` test: ``o exp(-sigma) >= alpha_min`` needs
    ``sigma <= L = ln(o / alpha_min)``, and on that ellipse ``|dx| <= sqrt(2 L Sigma_xx)``
    (``Sigma = conic^-1``, so ``Sigma_xx = c / det``, ``Sigma_yy = a / det``). A block
    outside this box holds no pixel the Gaussian is drawn on, so dropping it leaves every
    output and gradient as it was (gsplat's optional opacity-tightened boxes, its PR #597,
    rest on the same bound); ``L`` gets a slack of 0.01 (alpha within 1%) against rounding. A
    Gaussian with ``o < alpha_min`` or culled gets an empty box. Feature Gaussians are
    mostly faint (an untrained head starts them near sigmoid(opacity_bias) = sigmoid(-2) ~ 0.12),
    so this removes many (Gaussian, block) pairs.
    """
    dtype = projected.means2d.dtype
    if opacities is None:
        inf = jnp.where(projected.radii > 0, jnp.inf, 0.0).astype(dtype)
        return inf, inf
    # Binning is not differentiated: cut the graph at the inputs (no sqrt(0) tangents).
    conics, opacities = lax.stop_gradient(projected.conics), lax.stop_gradient(opacities)
    a, b, c = conics[:, 0], conics[:, 1], conics[:, 2]
    det = a * c - b * b
    ok = (projected.radii > 0) & (det > 0)
    det = jnp.where(ok, det, 1.0)
    level = jnp.log(jnp.maximum(opacities.astype(dtype), 1e-30) / cfg.alpha_min) + 0.01
    two_l = jnp.where(ok, 2.0 * jnp.maximum(level, 0.0), 0.0)
    return jnp.sqrt(two_l * jnp.maximum(c, 0.0) / det), jnp.sqrt(two_l * jnp.maximum(a, 0.0) / det)


def _ellipse_terms(
    projected: ProjectedGaussians, opacities: Float[Array, " N"], cfg: SplatConfig
) -> tuple[Float[Array, " N"], ...]:
    """Per Gaussian, what :func:`_reaches_block` reads: the conic ``(a, b, c)``, the mean
    ``(x, y)`` and the level ``L = ln(o / alpha_min) + 0.01``."""
    conics, means = lax.stop_gradient(projected.conics), lax.stop_gradient(projected.means2d)
    level = jnp.log(jnp.maximum(lax.stop_gradient(opacities).astype(means.dtype), 1e-30) / cfg.alpha_min) + 0.01
    return (
        jnp.maximum(conics[:, 0], 1e-30),
        conics[:, 1],
        jnp.maximum(conics[:, 2], 1e-30),
        means[:, 0],
        means[:, 1],
        level,
    )


def _reaches_block(
    a: Float[Array, " isect"],
    b: Float[Array, " isect"],
    c: Float[Array, " isect"],
    mx: Float[Array, " isect"],
    my: Float[Array, " isect"],
    level: Float[Array, " isect"],
    bx: Int[Array, " isect"],
    by: Int[Array, " isect"],
    cfg: SplatConfig,
) -> Bool[Array, " isect"]:
    """Whether a Gaussian (per slot: its conic ``a, b, c``, mean and level from
    :func:`_ellipse_terms`) passes the compositor's ``alpha >= alpha_min`` test at any pixel
    centre of compositor block ``(bx, by)``.

    The opacity-trimmed box of :func:`screen_extents` bounds the ellipse
    ``sigma <= L = ln(o / alpha_min)``; the blocks in its corners can still miss it (a quarter
    of a large round Gaussian's box, more for a thin slanted one). Here the least
    ``sigma = 0.5 (a dx^2 + 2 b dx dy + c dy^2)`` over the rectangle of the block's pixel
    centres is compared with ``L`` (slack 0.01, as the box): the form is convex with its
    minimum 0 at the mean, so outside the rectangle its least value lies on an edge, where it
    is a 1-D quadratic minimised in closed form. A block that fails holds no pixel the
    Gaussian is drawn on, so leaving it out changes no output or gradient.
    """
    bs = cfg.composite_tile
    lo_x = (bx * bs).astype(mx.dtype) + 0.5 - mx  # pixel-centre rectangle, relative to the mean
    lo_y = (by * bs).astype(my.dtype) + 0.5 - my
    hi_x, hi_y = lo_x + (bs - 1), lo_y + (bs - 1)

    def on_x_edge(x):  # least sigma on the edge dx = x, dy in [lo_y, hi_y]
        y = jnp.clip(-b * x / c, lo_y, hi_y)
        return 0.5 * (a * x * x + 2.0 * b * x * y + c * y * y)

    def on_y_edge(y):
        x = jnp.clip(-b * y / a, lo_x, hi_x)
        return 0.5 * (a * x * x + 2.0 * b * x * y + c * y * y)

    inside = (lo_x <= 0) & (hi_x >= 0) & (lo_y <= 0) & (hi_y >= 0)
    least = jnp.minimum(jnp.minimum(on_x_edge(lo_x), on_x_edge(hi_x)), jnp.minimum(on_y_edge(lo_y), on_y_edge(hi_y)))
    return inside | (least <= level)


def tile_rects(
    projected: ProjectedGaussians,
    height: int,
    width: int,
    cfg: SplatConfig,
    opacities: Float[Array, " N"] | None = None,
    extents: tuple[Float[Array, " N"], Float[Array, " N"]] | None = None,
) -> tuple[Int[Array, " N"], Int[Array, " N"], Int[Array, " N"], Int[Array, " N"]]:
    """Half-open box ``(x0, x1, y0, y1)`` of compositor blocks for each Gaussian: the blocks
    of its gsplat tiles that it can reach (:func:`screen_extents`, or the given per-axis
    half-widths ``extents`` in pixels, as the 2DGS projection computes them); empty when
    culled or, given ``opacities``, when it is too faint to be drawn."""
    blocks_y, blocks_x = cfg.tile_grid(height, width)
    ts, bs = float(cfg.tile_size), float(cfg.composite_tile)
    r = projected.radii.astype(projected.means2d.dtype)
    ex, ey = screen_extents(projected, cfg, opacities) if extents is None else extents

    def axis(m, e, n_blocks):
        lo = jnp.maximum(jnp.floor((m - r) / ts) * ts, m - e)  # gsplat's tiles, cut to reach
        hi = jnp.minimum(jnp.ceil((m + r) / ts) * ts, m + e)
        b0 = jnp.clip(jnp.floor(lo / bs), 0, n_blocks).astype(jnp.int32)
        b1 = jnp.clip(jnp.ceil(hi / bs), 0, n_blocks).astype(jnp.int32)
        return b0, jnp.maximum(b1, b0)

    x0, x1 = axis(projected.means2d[:, 0], ex, blocks_x)
    y0, y1 = axis(projected.means2d[:, 1], ey, blocks_y)
    drawn = (r > 0) & (ex > 0) & (ey > 0)  # culled Gaussians have radius 0
    return x0, jnp.where(drawn, x1, x0), y0, jnp.where(drawn, y1, y0)


def intersection_counts(
    projected: ProjectedGaussians,
    height: int,
    width: int,
    cfg: SplatConfig,
    opacities: Float[Array, " N"] | None = None,
    extents: tuple[Float[Array, " N"], Float[Array, " N"]] | None = None,
) -> Int[Array, " N"]:
    """Number of compositor blocks each Gaussian enters (0 when culled); without
    ``opacities`` or ``extents`` an upper bound (every block of its tiles)."""
    x0, x1, y0, y1 = tile_rects(projected, height, width, cfg, opacities, extents)
    return (x1 - x0) * (y1 - y0)


# Float32 bit patterns of positive numbers sort as int32s; +inf's is above every finite one.
_INF_BITS = 0x7F800000


def _depth_order_by_key(
    depths: Float[Array, " N"], drawn: Bool[Array, " N"]
) -> tuple[Int[Array, " N"], Int[Array, " N"]]:
    """:func:`depth_positions` by one int32 sort.

    Drawn depths are > ``near`` > 0, so their float32 bit patterns order as the depths;
    undrawn Gaussians get the distinct keys ``inf_bits + index`` after every drawn one. A
    single-array int32 sort is much faster than ``argsort`` on CPU; a Gaussian's position is
    the first place of its key among the sorted keys (binary search), plus, for equal
    depths (a few hundred pairs among 100k uniform float32 depths: the birthday bound), its
    rank by index among them: round k gives the k-th smallest index of every tie group the
    next place, so the loop runs as many rounds as the largest group.
    """
    n = depths.shape[0]
    iota = jnp.arange(n, dtype=jnp.int32)
    bits = lax.bitcast_convert_type(depths.astype(jnp.float32), jnp.int32)
    keys = jnp.where(drawn, bits, _INF_BITS + iota)
    first = jnp.searchsorted(lax.sort(keys), keys, side="left").astype(jnp.int32)

    def round_(state):
        k, rank, placed = state
        smallest = jnp.full((n,), n, jnp.int32).at[first].min(jnp.where(placed, n, iota))
        wins = ~placed & (smallest[first] == iota)
        return k + 1, jnp.where(wins, first + k, rank), placed | wins

    # ``first < 0`` is all False, built from the inputs so that under ``shard_map`` it has
    # the same (device-varying) type as the loop body's output.
    _, rank, _ = lax.while_loop(lambda s: ~jnp.all(s[2]), round_, (jnp.int32(0), first, first < 0))
    return jnp.zeros((n,), jnp.int32).at[rank].set(iota, unique_indices=True), rank


def depth_positions(depths: Float[Array, " N"], drawn: Bool[Array, " N"]) -> tuple[Int[Array, " N"], Int[Array, " N"]]:
    """``(order, position)``: the indices of the drawn Gaussians by increasing depth (ties by
    index: a stable sort), then the undrawn ones by index; and each Gaussian's place in that
    order (the inverse permutation, ``order[position] == arange(N)``).

    Float32 depths with fewer than 2**23 Gaussians take the int32 key sort of
    :func:`_depth_order_by_key`; others a stable ``argsort``.
    """
    depths = lax.stop_gradient(depths)  # an order: nothing to differentiate
    if depths.dtype == jnp.float32 and depths.shape[0] < (1 << 31) - _INF_BITS:
        return _depth_order_by_key(depths, drawn)
    order = jnp.argsort(jnp.where(drawn, depths, jnp.inf), stable=True).astype(jnp.int32)
    iota = jnp.arange(order.shape[0], dtype=jnp.int32)
    return order, jnp.zeros_like(order).at[order].set(iota, unique_indices=True)


def depth_order(depths: Float[Array, " N"], drawn: Bool[Array, " N"]) -> Int[Array, " N"]:
    """The first of :func:`depth_positions`: Gaussian indices in depth order."""
    return depth_positions(depths, drawn)[0]


def _saturating_add(a: Int[Array, " ..."], b: Int[Array, " ..."]) -> Int[Array, " ..."]:
    return jnp.minimum(a + b, SATURATION)


def _inclusive_prefix_sum(counts: Int[Array, " N"], num_tiles: int) -> Int[Array, " N"]:
    """Running total of intersection counts, saturating at ``SATURATION``.

    Each count is at most ``num_tiles``, so a plain int32 cumsum is exact whenever
    ``N * num_tiles < 2**31`` (static); only larger problems pay for the saturating scan.
    """
    if counts.shape[0] * num_tiles < 2**31:
        return jnp.cumsum(counts, dtype=jnp.int32)
    return lax.associative_scan(_saturating_add, counts)


def bin_gaussians(
    projected: ProjectedGaussians,
    height: int,
    width: int,
    capacity: int,
    cfg: SplatConfig,
    opacities: Float[Array, " N"] | None = None,
    extents: tuple[Float[Array, " N"], Float[Array, " N"]] | None = None,
) -> TileBins:
    """Bin projected Gaussians into depth-sorted per-tile lists of ``capacity`` slots.

    ``opacities`` (the largest of any copy that will be composited from these bins) trims
    each box to where the Gaussian can be drawn (:func:`screen_extents`) and drops the
    blocks its ellipse misses; ``extents`` (per-axis half-widths, pixels) trims the boxes
    instead, for footprints that are not the conic's ellipse (2DGS)."""
    n = projected.radii.shape[0]
    tiles_y, tiles_x = cfg.tile_grid(height, width)
    num_tiles = tiles_y * tiles_x
    x0, x1, y0, y1 = tile_rects(projected, height, width, cfg, opacities, extents)
    counts = (x1 - x0) * (y1 - y0)

    with jax.named_scope("splat_sort"):
        order, position = depth_positions(projected.depths, counts > 0)
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
    rank = slots - starts[src]

    # Per-Gaussian values are put in depth order once and read by ``src`` (non-decreasing,
    # so the reads are sequential). A scatter to ``position``, not a gather by ``order``:
    # XLA:CPU drops optimization barriers before fusing and would fuse ``v[order][src]``
    # into the per-slot loop, recomputing every value behind two random reads per slot
    # (docs/speed-cpu.md, "Per-Gaussian values by a scatter"); a scatter's result is always
    # materialised.
    def to_depth_order(values: list[Array]) -> list[Array]:
        stacked = jnp.stack(values, axis=-1)
        moved = jnp.zeros_like(stacked).at[position].set(stacked, unique_indices=True)
        return [moved[:, i] for i in range(len(values))]

    x0s, y0s, box_w = (v[src] for v in to_depth_order([x0, y0, jnp.maximum(x1 - x0, 1)]))
    bx, by = x0s + rank % box_w, y0s + rank // box_w
    used = slots < needed
    if opacities is not None:  # the box's blocks that the ellipse misses hold nothing
        ellipse = to_depth_order(list(_ellipse_terms(projected, opacities, cfg)))
        used = used & _reaches_block(*(v[src] for v in ellipse), bx, by, cfg)  # pyright: ignore[reportCallIssue] -- the unpacked tuple holds the other arguments
    tile = jnp.where(used, by * tiles_x + bx, num_tiles)  # sentinel sorts after every tile

    with jax.named_scope("splat_sort"):
        if (num_tiles + 1) * n < 2**31:
            # One int32 key (block, depth rank): src is the slot's position in depth order.
            key = lax.sort(tile * n + src)
            sorted_tile, sorted_gid = key // n, order[key % n]
        else:
            sorted_tile, sorted_gid = lax.sort((tile, order[src]), num_keys=1, is_stable=True)
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
