"""Front-to-back alpha compositing of binned Gaussians that carry feature vectors.

Per pixel p and its tile's depth-sorted list, gsplat's rule: with the Mahalanobis
half-distance ``sigma = 0.5 (a (dx + q dy)^2 + s dy^2)`` (d = mean2d - pixel centre; the
conic with its square completed, see :mod:`.projection`; ``sigma >= 0``, so gsplat's
``sigma < 0`` skip never applies), ``alpha = min(alpha_max, o exp(-sigma))``; entries with
``alpha < alpha_min`` are skipped; the pixel stops at the first entry whose
``T (1 - alpha) <= t_min`` (that entry is not used). Outputs: ``sum_i w_i f_i`` with
``w_i = alpha_i T_i`` and the final transmittance T.

Axis names: ``group`` blocks advanced together, ``pix`` the pixels of a block
(``composite_tile`` squared, 64 by default), ``chunk`` list entries per step, ``isect``
the binning buffer, C channels (features + depth). "Tile" below means a compositor block
(:mod:`.config`).

Work layout: tiles are sorted by list length and cut into groups of ``tiles_per_group``;
``lax.map`` runs one group at a time and each group runs a ``while_loop`` over chunks of
``chunk_size`` list entries until its longest list is exhausted or all its pixels have
stopped. A chunk is evaluated as ``[group, chunk, pix]`` arrays:

* transmittances are cumulative products of ``1 - alpha`` (:func:`_cumulative`);
* features are accumulated by ``weights @ features`` per tile (F costs a contraction,
  not sequential steps).

Gradients: a ``custom_vjp`` (the transmittance chain is not differentiated by autodiff,
which would store every chunk's state). The backward pass walks each group's chunks back
to front, recovers ``T`` before each entry by dividing the pixel's transmittance after the
chunk by a reverse cumulative product of ``1 - alpha`` (``1 - alpha >= 1 - alpha_max``), and
carries
``S = sum_{j later} w_j (f_j . g) + g_T T_final``, which gives
``dL/dalpha_i = T_i (f_i . g) - S_i / (1 - alpha_i)`` without cancellation (gsplat's
backward, which also keeps no per-pixel history). Memory of the backward pass is
O(N + pixels), independent of the number of chunks.

Batches: ``jax.vmap`` of a ``while_loop`` whose trip count differs across the batch runs
every element to the longest count and selects each loop carry on every step, which for
the backward pass is a copy of the whole [N, C] gradient per chunk. The group loops
therefore run one batch element after another under ``vmap``
(:func:`~llrmpp_jax.splat.sequential.sequential_over_batch`).
"""

from __future__ import annotations

import functools
from collections.abc import Callable
from typing import NamedTuple

import jax
import jax.numpy as jnp
from jax import lax

from llrmpp_jax.array_typing import Array, Bool, Float, Int
from llrmpp_jax.splat.binning import TileBins
from llrmpp_jax.splat.config import SplatConfig
from llrmpp_jax.splat.sequential import sequential_over_batch

_HIGHEST = lax.Precision.HIGHEST


class _Groups(NamedTuple):
    """Tiles in processing order, ``[groups, group]`` each."""

    tile_ids: Int[Array, "groups group"]  # tile index (num_tiles for padding)
    starts: Int[Array, "groups group"]
    counts: Int[Array, "groups group"]


class _Chunk(NamedTuple):
    """One chunk of K list entries evaluated on the P pixels of G tiles."""

    gid: Int[Array, "group chunk"]  # Gaussian index (0 where the slot is past the list)
    valid: Bool[Array, "group chunk"]  # slot inside the tile's list
    dx: Float[Array, "group chunk pix"]
    dy: Float[Array, "group chunk pix"]
    quad: Float[Array, "group chunk 3"]  # (a, q, s) of the quadratic form
    opacity: Float[Array, "group chunk"]
    vis: Float[Array, "group chunk pix"]  # exp(-sigma)
    alpha: Float[Array, "group chunk pix"]  # min(alpha_max, o exp(-sigma))
    active: Bool[Array, "group chunk pix"]  # valid and alpha >= alpha_min


def _running(
    xs: list[Float[Array, " ..."]], op: Callable, identity: float
) -> tuple[list[Float[Array, " ..."]], Float[Array, " ..."]]:
    """Exclusive running ``op`` over a list of equal-shaped arrays, and the total."""
    out, total = [], None
    for x in xs:
        out.append(jnp.full_like(x, identity) if total is None else total)
        total = x if total is None else op(total, x)
    return out, total  # pyright: ignore[reportReturnType] -- total is set whenever xs is not empty


def _cumulative(
    x: Float[Array, "group chunk pix"],
    op: Callable,
    identity: float,
    exclusive: bool = False,
    reverse: bool = False,
) -> Float[Array, "group chunk pix"]:
    """Cumulative ``op`` (``jnp.multiply`` or ``jnp.add``) along the chunk axis.

    ``exclusive`` leaves out the entry itself (the first value is ``identity``),
    ``reverse`` runs from the end.

    Two levels of unrolled running products: within blocks of 4 entries, then across the
    blocks' totals, which XLA fuses into a few element-wise passes. On CPU that is faster
    than ``lax.associative_scan`` (log2(K) passes) or one chain of K, and it shortens the
    splatter's forward and backward; blocks of 8 made XLA fuse the backward badly, and
    ``lax.cumprod`` lowers to a ``reduce_window`` of K operations per output on CPU
    (docs/lab-notes.md, "The splatter's running products").
    """
    if reverse:
        return _cumulative(x[:, ::-1], op, identity, exclusive)[:, ::-1]
    g, k, p = x.shape
    b = 4 if k % 4 == 0 else 1
    blocks = x.reshape(g, k // b, b, p)
    within, totals = _running([blocks[:, :, i] for i in range(b)], op, identity)
    inner = jnp.stack(within if exclusive else within[1:] + [totals], axis=2)
    before, _ = _running([totals[:, j] for j in range(k // b)], op, identity)
    return op(inner, jnp.stack(before, axis=1)[:, :, None, :]).reshape(g, k, p)


def _make_groups(bins: TileBins, cfg: SplatConfig) -> _Groups:
    num_tiles = bins.tile_count.shape[0]
    g = min(cfg.tiles_per_group, num_tiles)
    num_groups = -(-num_tiles // g)
    order = jnp.argsort(-bins.tile_count, stable=True).astype(jnp.int32)
    pad = jnp.full((num_groups * g - num_tiles,), num_tiles, jnp.int32)
    tile_ids = jnp.concatenate([order, pad])
    zero = jnp.zeros((1,), jnp.int32)
    starts = jnp.concatenate([bins.tile_start, zero])[tile_ids]
    counts = jnp.concatenate([bins.tile_count, zero])[tile_ids]
    shape = (num_groups, g)
    return _Groups(tile_ids.reshape(shape), starts.reshape(shape), counts.reshape(shape))


def _pixels(
    tile_ids: Int[Array, " group"], height: int, width: int, cfg: SplatConfig, dtype: jnp.dtype
) -> tuple[Float[Array, "group pix"], Float[Array, "group pix"], Bool[Array, "group pix"]]:
    """Pixel centres (x, y) of each tile (row-major inside the tile) and in-canvas mask."""
    ts = cfg.composite_tile
    tiles_x = cfg.tile_grid(height, width)[1]
    local = jnp.arange(ts * ts, dtype=jnp.int32)
    ix = (tile_ids % tiles_x * ts)[:, None] + (local % ts)[None, :]
    iy = (tile_ids // tiles_x * ts)[:, None] + (local // ts)[None, :]
    live = (ix < width) & (iy < height)  # padding tiles have iy >= height
    return ix.astype(dtype) + 0.5, iy.astype(dtype) + 0.5, live


def _eval_chunk(
    c: Int[Array, ""],
    starts: Int[Array, " group"],
    counts: Int[Array, " group"],
    gaussian_ids: Int[Array, " isect"],
    geometry: Float[Array, "N 5"],
    opacities: Float[Array, " N"],
    px: Float[Array, "group pix"],
    py: Float[Array, "group pix"],
    cfg: SplatConfig,
) -> _Chunk:
    k = cfg.chunk_size
    offs = c * k + jnp.arange(k, dtype=jnp.int32)
    valid = offs[None, :] < counts[:, None]
    slot = jnp.minimum(starts[:, None] + offs[None, :], gaussian_ids.shape[0] - 1)
    gid = jnp.where(valid, gaussian_ids[slot], 0)
    geo = geometry[gid]
    opacity = opacities[gid]
    dx = geo[:, :, 0, None] - px[:, None, :]
    dy = geo[:, :, 1, None] - py[:, None, :]
    quad = geo[:, :, 2:]
    u = dx + quad[:, :, 1, None] * dy
    sigma = 0.5 * (quad[:, :, 0, None] * u * u + quad[:, :, 2, None] * dy * dy)
    vis = jnp.exp(-sigma)
    alpha = jnp.minimum(cfg.alpha_max, opacity[:, :, None] * vis)
    active = valid[:, :, None] & (alpha >= cfg.alpha_min)
    return _Chunk(gid, valid, dx, dy, quad, opacity, vis, alpha, active)


def _typed_zero(dtype: jnp.dtype, *arrays: Array) -> Array:
    """A scalar 0 that depends on every input, so loop carries built from constants have
    the same type as the loop body's outputs under ``shard_map`` (whose values vary over
    the mesh axis); XLA folds it away everywhere else."""
    return sum((jnp.sum(a.reshape(-1)[:0]).astype(dtype) for a in arrays), jnp.zeros((), dtype))


def _forward_group(
    geometry: Float[Array, "N 5"],
    opacities: Float[Array, " N"],
    features: Float[Array, "N C"],
    gaussian_ids: Int[Array, " isect"],
    group: tuple[Int[Array, " group"], Int[Array, " group"], Int[Array, " group"]],
    height: int,
    width: int,
    cfg: SplatConfig,
) -> tuple[Float[Array, "group C pix"], Float[Array, "group pix"], Int[Array, "group pix"]]:
    """Composite one tile group: features (channel-major), final T and ``last`` (1 + last
    used entry)."""
    tile_ids, starts, counts = group
    k = cfg.chunk_size
    dtype = geometry.dtype
    px, py, live = _pixels(tile_ids, height, width, cfg, dtype)
    num_chunks = (jnp.max(counts) + k - 1) // k
    g, p = px.shape
    karange = jnp.arange(1, k + 1, dtype=jnp.int32)[None, :, None]

    def cond(state):
        c, _, done, _, _ = state
        return (c < num_chunks) & jnp.any(~done)

    def body(state):
        c, trans, done, acc, last = state
        ch = _eval_chunk(c, starts, counts, gaussian_ids, geometry, opacities, px, py, cfg)
        a = jnp.where(ch.active, ch.alpha, 0.0)
        om = 1.0 - a
        t_in = trans[:, None, :] * _cumulative(om, jnp.multiply, 1.0, exclusive=True)
        stop = ch.active & (t_in * om <= cfg.t_min)
        incl = ch.active & ~stop & ~done[:, None, :]
        w = jnp.where(incl, a * t_in, 0.0)
        # Channel-major accumulator: XLA:CPU runs this contraction faster than "->gpc".
        acc = acc + jnp.einsum("gkp,gkc->gcp", w, features[ch.gid], precision=_HIGHEST)
        trans = trans * jnp.prod(jnp.where(incl, om, 1.0), axis=1)
        done = done | jnp.any(stop, axis=1)
        used = jnp.max(jnp.where(incl, karange, 0), axis=1)
        last = jnp.where(used > 0, c * k + used, last)
        return c + 1, trans, done, acc, last

    zero = _typed_zero(dtype, geometry, opacities, features, gaussian_ids, starts, counts)
    init = (
        jnp.zeros((), jnp.int32),
        jnp.ones((g, p), dtype) + zero,
        ~live | (zero != 0),
        jnp.zeros((g, features.shape[1], p), dtype) + zero,
        jnp.zeros((g, p), jnp.int32) + zero.astype(jnp.int32),
    )
    _, trans, _, acc, last = lax.while_loop(cond, body, init)
    return acc, trans, last


def _backward_group(
    geometry: Float[Array, "N 5"],
    opacities: Float[Array, " N"],
    features: Float[Array, "N C"],
    gaussian_ids: Int[Array, " isect"],
    group: tuple[Int[Array, " group"], Int[Array, " group"], Int[Array, " group"]],
    trans_final: Float[Array, "group pix"],
    last: Int[Array, "group pix"],
    g_feat: Float[Array, "group C pix"],
    g_trans: Float[Array, "group pix"],
    grads: tuple[Float[Array, "N 5"], Float[Array, " N"], Float[Array, "N C"]],
    height: int,
    width: int,
    cfg: SplatConfig,
) -> tuple[Float[Array, "N 5"], Float[Array, " N"], Float[Array, "N C"]]:
    """Add one tile group's contribution to the gradients of geometry, opacity, features."""
    tile_ids, starts, counts = group
    k = cfg.chunk_size
    n = geometry.shape[0]
    px, py, _ = _pixels(tile_ids, height, width, cfg, geometry.dtype)
    num_chunks = (jnp.max(last) + k - 1) // k

    def body(state):
        c, t_end, s_after, (d_geo, d_op, d_feat) = state
        ch = _eval_chunk(c, starts, counts, gaussian_ids, geometry, opacities, px, py, cfg)
        offs = c * k + jnp.arange(k, dtype=jnp.int32)
        incl = ch.active & (offs[None, :, None] < last[:, None, :])
        a = jnp.where(incl, ch.alpha, 0.0)
        om = 1.0 - a
        # T before entry i = T_end / prod_{j >= i} (1 - alpha_j), 1 - alpha >= 1 - alpha_max.
        t_in = t_end[:, None, :] / _cumulative(om, jnp.multiply, 1.0, reverse=True)
        w = a * t_in
        f = features[ch.gid]
        fg = jnp.einsum("gkc,gcp->gkp", f, g_feat, precision=_HIGHEST)
        wfg = w * fg
        later = _cumulative(wfg, jnp.add, 0.0, exclusive=True, reverse=True)
        d_alpha = jnp.where(incl, t_in * fg - (s_after[:, None, :] + later) / om, 0.0)
        unclamped = ch.opacity[:, :, None] * ch.vis <= cfg.alpha_max
        d_sigma = jnp.where(unclamped, -ch.alpha * d_alpha, 0.0)
        d_opacity = jnp.sum(jnp.where(unclamped, ch.vis * d_alpha, 0.0), axis=2)
        qa, qq, qs = (ch.quad[:, :, i, None] for i in range(3))
        u = ch.dx + qq * ch.dy
        d_u = d_sigma * qa * u  # dL/du, u = dx + q dy
        d_geo_chunk = jnp.stack(
            [
                jnp.sum(d_u, axis=2),
                jnp.sum(d_u * qq + d_sigma * qs * ch.dy, axis=2),
                jnp.sum(0.5 * d_sigma * u * u, axis=2),
                jnp.sum(d_u * ch.dy, axis=2),
                jnp.sum(0.5 * d_sigma * ch.dy * ch.dy, axis=2),
            ],
            axis=-1,
        )
        d_feat_chunk = jnp.einsum("gkp,gcp->gkc", w, g_feat, precision=_HIGHEST)
        idx = jnp.where(ch.valid, ch.gid, n).reshape(-1)
        d_geo = d_geo.at[idx].add(d_geo_chunk.reshape(-1, 5), mode="drop")
        d_op = d_op.at[idx].add(d_opacity.reshape(-1), mode="drop")
        d_feat = d_feat.at[idx].add(d_feat_chunk.reshape(-1, f.shape[-1]), mode="drop")
        return c - 1, t_in[:, 0, :], s_after + jnp.sum(wfg, axis=1), (d_geo, d_op, d_feat)

    init = (num_chunks - 1, trans_final, g_trans * trans_final, grads)
    _, _, _, grads = lax.while_loop(lambda s: s[0] >= 0, body, init)
    return grads


def _to_canvas(tiles: Float[Array, "tiles C pix"], height: int, width: int, cfg: SplatConfig) -> Float[Array, "H W C"]:
    """``[T, C, P]`` channel-major tiles (the compositor's accumulators) to a ``[H, W, C]``
    canvas in one transpose."""
    ts = cfg.composite_tile
    tiles_y, tiles_x = cfg.tile_grid(height, width)
    c = tiles.shape[1]
    x = tiles.reshape(tiles_y, tiles_x, c, ts, ts).transpose(0, 3, 1, 4, 2)
    return x.reshape(tiles_y * ts, tiles_x * ts, c)[:height, :width]


def _from_canvas(canvas: Float[Array, "H W C"], height: int, width: int, cfg: SplatConfig) -> Float[Array, "_ C pix"]:
    """Inverse of :func:`_to_canvas` (padding filled with zeros), plus one zero tile:
    ``[tiles + 1, C, pix]``."""
    ts = cfg.composite_tile
    tiles_y, tiles_x = cfg.tile_grid(height, width)
    c = canvas.shape[2]
    x = jnp.pad(canvas, [(0, tiles_y * ts - height), (0, tiles_x * ts - width), (0, 0)])
    x = x.reshape(tiles_y, ts, tiles_x, ts, c).transpose(0, 2, 4, 1, 3).reshape(tiles_y * tiles_x, c, ts * ts)
    return jnp.concatenate([x, jnp.zeros_like(x[:1])], axis=0)


@functools.cache
def _forward_fn(height: int, width: int, cfg: SplatConfig) -> Callable:
    """All groups' forward pass: ``(geometry, opacities, features, gaussian_ids, groups) ->
    (features [H, W, C], T [H, W]), (per-group T, last)``, sequential under vmap."""

    @jax.named_scope("splat_composite")
    def forward(geometry, opacities, features, gaussian_ids, groups):
        def one(group):
            return _forward_group(geometry, opacities, features, gaussian_ids, group, height, width, cfg)

        acc, trans, last = lax.map(one, tuple(groups))
        tiles_y, tiles_x = cfg.tile_grid(height, width)
        # Position of every real tile in processing order (the inverse permutation).
        where_tile = jnp.argsort(groups.tile_ids.reshape(-1), stable=True)[: tiles_y * tiles_x]
        p = acc.shape[-1]
        feat = _to_canvas(acc.reshape(-1, acc.shape[2], p)[where_tile], height, width, cfg)
        t_canvas = _to_canvas(trans.reshape(-1, 1, p)[where_tile], height, width, cfg)[..., 0]
        return (feat, t_canvas), (trans, last)

    return sequential_over_batch(forward)


@functools.cache
def _backward_fn(height: int, width: int, cfg: SplatConfig) -> Callable:
    """All groups' backward pass: ``(residuals..., cotangents) -> (d_geometry, d_opacities,
    d_features)``, sequential under vmap."""

    @jax.named_scope("splat_composite")
    def backward(geometry, opacities, features, gaussian_ids, groups, trans, last, g_feat, g_trans):
        flat_ids = groups.tile_ids.reshape(-1)
        # Channel-major, as the forward's accumulator.
        gf = _from_canvas(g_feat, height, width, cfg)[flat_ids]
        gf = gf.reshape(trans.shape[:-1] + gf.shape[1:])
        gt = _from_canvas(g_trans[..., None], height, width, cfg)[flat_ids].reshape(trans.shape)

        def step(grads, xs):
            group, t_fin, lst, gfe, gtr = xs
            new = _backward_group(
                geometry,
                opacities,
                features,
                gaussian_ids,
                group,
                t_fin,
                lst,
                gfe,
                gtr,
                grads,
                height,
                width,
                cfg,
            )
            return new, None

        zero = _typed_zero(geometry.dtype, geometry, opacities, features, gaussian_ids, trans, g_feat, g_trans)
        zeros = tuple(jnp.zeros_like(x) + zero for x in (geometry, opacities, features))
        grads, _ = lax.scan(step, zeros, (tuple(groups), trans, last, gf, gt))
        return grads

    return sequential_over_batch(backward)


@functools.partial(jax.custom_vjp, nondiff_argnums=(0, 1, 2))
def _composite(height, width, cfg, geometry, opacities, features, gaussian_ids, groups):
    out, _ = _forward_fn(height, width, cfg)(geometry, opacities, features, gaussian_ids, groups)
    return out


def _composite_fwd(height, width, cfg, geometry, opacities, features, gaussian_ids, groups):
    out, (trans, last) = _forward_fn(height, width, cfg)(geometry, opacities, features, gaussian_ids, groups)
    return out, (geometry, opacities, features, gaussian_ids, groups, trans, last)


def _composite_bwd(height, width, cfg, res, cotangents):
    g_feat, g_trans = cotangents
    d_geo, d_op, d_feat = _backward_fn(height, width, cfg)(*res, g_feat, g_trans)
    none_groups = _Groups(None, None, None)  # pyright: ignore[reportArgumentType] -- the integer tile lists have no cotangent: None
    return d_geo, d_op, d_feat, None, none_groups


_composite.defvjp(_composite_fwd, _composite_bwd)


def composite(
    means2d: Float[Array, "N 2"],
    quad_form: Float[Array, "N 3"],
    opacities: Float[Array, " N"],
    features: Float[Array, "N C"],
    bins: TileBins,
    height: int,
    width: int,
    cfg: SplatConfig = SplatConfig(),
) -> tuple[Float[Array, "H W C"], Float[Array, "H W"]]:
    """Composite binned Gaussians front to back onto an ``height x width`` canvas.

    Returns ``(sum_i w_i f_i [H, W, C], final transmittance [H, W])``; no background is
    added. ``quad_form`` is :attr:`ProjectedGaussians.quad_form`. Differentiable w.r.t.
    ``means2d``, ``quad_form``, ``opacities`` and ``features``.
    """
    geometry = jnp.concatenate([means2d, quad_form], axis=-1)
    groups = _make_groups(bins, cfg)
    return _composite(height, width, cfg, geometry, opacities, features, bins.gaussian_ids, groups)
