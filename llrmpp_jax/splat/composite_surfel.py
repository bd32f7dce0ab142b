"""Front-to-back compositing of binned surfels (2DGS): features, depth, distortion, median.

Per pixel p (centre ``(x, y)``) and its block's depth-sorted list (:mod:`.binning`), for
each surfel i: the ray-splat intersection ``(u, v)`` through the ray transform
(:mod:`.surfel`), ``G3 = exp(-(u^2 + v^2) / 2)``, the 2DGS low-pass filter
``G2 = exp(-|d|^2)`` (``d = means2d - p``: gsplat's ``FILTER_INV_SQUARE_2DGS`` 2, a screen
Gaussian of variance 1/2 px^2), and ``alpha = min(alpha_max, o max(G3, G2))`` (gsplat's
``sigma = 0.5 min(u^2 + v^2, 2 |d|^2)``). Then the same rule as the 3DGS compositor
(:mod:`.composite`): entries with ``alpha < alpha_min`` are skipped, the pixel stops at the
first entry whose ``T (1 - alpha) <= t_min`` (not used), ``w_i = alpha_i T_i``.

A ray (nearly) parallel to the plane meets it at infinity: where ``|u|`` or ``|v|`` would
exceed 1e6 the surfel kernel is taken as 0 and only the filter remains (gsplat skips a pair
whose intersection is exactly at infinity altogether; the two differ on a set of measure
zero).

Depth ``z_i(p)``: the centre's camera z (``depth="center"``, gsplat's ``rasterization_2dgs``)
or the intersection's camera z ``M2 . (u, v, 1)`` (``depth="intersection"``, the 2DGS
paper's rasterizer: there, as in its code, the centre z where the filter wins, so a pixel
that sees a surfel only through the filter does not get the depth of a far, grazing hit);
either way the lists are sorted by centre z. Outputs per pixel:

* ``sum_i w_i f_i`` (features, with the camera-frame normals as three more channels) and T;
* depth ``sum_i w_i z_i``;
* distortion ``sum_i 2 w_i (z_i (1 - T_i) - sum_{j<i} w_j z_j) = sum_{j<i} 2 w_i w_j
  (z_i - z_j)`` (gsplat's L1 form; ``sum_{i,j} w_i w_j |z_i - z_j|`` when z grows along the
  list, as centre z does);
* median depth: ``z`` of the last used entry with ``T_i > 0.5`` (gsplat's), 0 if none.

Work layout: as :mod:`.composite` (its tile groups, pixel blocks and running products).

Gradients: a ``custom_vjp`` that walks each group's chunks back to front (memory
O(N + pixels)). A chunk maps the pixel state before it, ``(T, Z = sum w z)``, and its
entries' parameters to the state after it and its additive contributions to the outputs; the
state before is recovered from the state after (``T`` by dividing by the chunk's product of
``1 - alpha >= 1 - alpha_max``, ``Z`` by subtracting the chunk's ``sum w z``), and the
chunk's VJP (JAX autodiff of that one chunk, recomputed) carries the state's cotangent back
and gives the entries' gradients. The median's gradient goes to the depth of the entry the
forward pass chose (its index is kept, as gsplat keeps ``median_ids``).
"""

from __future__ import annotations

import functools
from collections.abc import Callable

import jax
import jax.numpy as jnp
from jax import lax

from llrmpp_jax.array_typing import Array, Bool, Float
from llrmpp_jax.splat.binning import TileBins
from llrmpp_jax.splat.composite import (
    _cumulative,
    _from_canvas,
    _Groups,
    _make_groups,
    _pixels,
    _to_canvas,
    _typed_zero,
)
from llrmpp_jax.splat.config import SplatConfig
from llrmpp_jax.splat.sequential import sequential_over_batch

_HIGHEST = lax.Precision.HIGHEST
DEPTH_MODES = ("center", "intersection")
# gsplat's FILTER_INV_SQUARE_2DGS: the filter's exponent is this times |d|^2 / 2.
FILTER_INV_SQUARE = 2.0
# Beyond this |u| or |v| the intersection is treated as at infinity (kernel 0).
_FAR_UV = 1e6
# Per-surfel geometry row: means2d (2) then the ray transform's rows M0, M1, M2 (9).
GEOMETRY_SIZE = 11


def _kernel(
    geo: Float[Array, "group chunk 11"],
    opacity: Float[Array, "group chunk"],
    px: Float[Array, "group pix"],
    py: Float[Array, "group pix"],
    cfg: SplatConfig,
    depth: str,
) -> tuple[Float[Array, "group chunk pix"], Float[Array, "group chunk pix"], Float[Array, "group chunk pix"]]:
    """``(alpha, o max(G3, G2), z)`` of each entry at each pixel of its block."""
    x, y = px[:, None, :], py[:, None, :]

    def g(i):
        return geo[:, :, i, None]

    # h_u = x M2 - M0, h_v = y M2 - M1; (c_x, c_y, c_z) = h_u x h_v.
    hu = [x * g(8 + j) - g(2 + j) for j in range(3)]
    hv = [y * g(8 + j) - g(5 + j) for j in range(3)]
    c_x = hu[1] * hv[2] - hu[2] * hv[1]
    c_y = hu[2] * hv[0] - hu[0] * hv[2]
    c_z = hu[0] * hv[1] - hu[1] * hv[0]
    finite = (jnp.abs(c_x) < _FAR_UV * jnp.abs(c_z)) & (jnp.abs(c_y) < _FAR_UV * jnp.abs(c_z))
    c_z = jnp.where(finite, c_z, 1.0)
    u = jnp.where(finite, c_x / c_z, _FAR_UV)
    v = jnp.where(finite, c_y / c_z, _FAR_UV)
    dx, dy = g(0) - x, g(1) - y
    w3, w2 = u * u + v * v, FILTER_INV_SQUARE * (dx * dx + dy * dy)
    raw = opacity[:, :, None] * jnp.exp(-0.5 * jnp.minimum(w3, w2))
    alpha = jnp.minimum(cfg.alpha_max, raw)
    if depth == "center":
        z = jnp.broadcast_to(g(10), alpha.shape)
    else:
        z = jnp.where(finite & (w3 <= w2), u * g(8) + v * g(9) + g(10), g(10))
    return alpha, raw, z


def _terms(
    t0: Float[Array, "group pix"],
    z0: Float[Array, "group pix"],
    alpha: Float[Array, "group chunk pix"],
    z: Float[Array, "group chunk pix"],
    feat: Float[Array, "group chunk C"],
    incl: Bool[Array, "group chunk pix"],
    median_hit: Bool[Array, "group chunk pix"],
):
    """One chunk's composite given the state ``(T, Z)`` before it: ``((T, Z) after,
    (features [g, C, p], depth, distortion, median) contributions), T before each entry``."""
    a = jnp.where(incl, alpha, 0.0)
    om = 1.0 - a
    t_in = t0[:, None, :] * _cumulative(om, jnp.multiply, 1.0, exclusive=True)
    w = a * t_in
    wz = w * z
    z_in = z0[:, None, :] + _cumulative(wz, jnp.add, 0.0, exclusive=True)
    acc = jnp.einsum("gkp,gkc->gcp", w, feat, precision=_HIGHEST)
    depth = jnp.sum(wz, axis=1)
    distortion = 2.0 * jnp.sum(w * (z * (1.0 - t_in) - z_in), axis=1)
    median = jnp.sum(jnp.where(median_hit, z, 0.0), axis=1)
    t1 = t0 * jnp.prod(om, axis=1)
    return (t1, z0 + depth), (acc, depth, distortion, median), t_in


def _gather(c, starts, counts, gaussian_ids, cfg):
    """Slot ids of chunk c of each block: ``(gid, valid, offsets)``."""
    k = cfg.chunk_size
    offs = c * k + jnp.arange(k, dtype=jnp.int32)
    valid = offs[None, :] < counts[:, None]
    slot = jnp.minimum(starts[:, None] + offs[None, :], gaussian_ids.shape[0] - 1)
    return jnp.where(valid, gaussian_ids[slot], 0), valid, offs


def _forward_group(geometry, opacities, features, gaussian_ids, group, height, width, cfg, depth):
    """Composite one block group: ``(features [g, C, p], T, depth, distortion, median,
    last, median_last)`` (``last``/``median_last``: 1 + index of the last used / median entry)."""
    tile_ids, starts, counts = group
    k = cfg.chunk_size
    dtype = geometry.dtype
    px, py, live = _pixels(tile_ids, height, width, cfg, dtype)
    num_chunks = (jnp.max(counts) + k - 1) // k
    g, p = px.shape
    karange = jnp.arange(1, k + 1, dtype=jnp.int32)[None, :, None]

    def cond(state):
        return (state[0] < num_chunks) & jnp.any(~state[2])

    def body(state):
        c, trans, done, zsum, acc, dist, med, last, med_last = state
        gid, valid, _ = _gather(c, starts, counts, gaussian_ids, cfg)
        alpha, _, z = _kernel(geometry[gid], opacities[gid], px, py, cfg, depth)
        active = valid[:, :, None] & (alpha >= cfg.alpha_min)
        om = 1.0 - jnp.where(active, alpha, 0.0)
        t_try = trans[:, None, :] * _cumulative(om, jnp.multiply, 1.0, exclusive=True)
        stop = active & (t_try * om <= cfg.t_min)
        incl = active & ~stop & ~done[:, None, :]
        none = jnp.zeros_like(incl)
        (trans, zsum), (a_c, _, d_c, _), t_in = _terms(trans, zsum, alpha, z, features[gid], incl, none)
        sel = jnp.max(jnp.where(incl & (t_in > 0.5), karange, 0), axis=1)
        z_sel = jnp.take_along_axis(z, jnp.maximum(sel - 1, 0)[:, None, :], axis=1)[:, 0, :]
        med = jnp.where(sel > 0, z_sel, med)
        med_last = jnp.where(sel > 0, c * k + sel, med_last)
        used = jnp.max(jnp.where(incl, karange, 0), axis=1)
        last = jnp.where(used > 0, c * k + used, last)
        done = done | jnp.any(stop, axis=1)
        return c + 1, trans, done, zsum, acc + a_c, dist + d_c, med, last, med_last

    zero = _typed_zero(dtype, geometry, opacities, features, gaussian_ids, starts, counts)
    plane = jnp.zeros((g, p), dtype) + zero
    izero = jnp.zeros((g, p), jnp.int32) + zero.astype(jnp.int32)
    init = (
        jnp.zeros((), jnp.int32),
        plane + 1.0,
        ~live | (zero != 0),
        plane,
        jnp.zeros((g, features.shape[1], p), dtype) + zero,
        plane,
        plane,
        izero,
        izero,
    )
    _, trans, _, zsum, acc, dist, med, last, med_last = lax.while_loop(cond, body, init)
    return acc, trans, zsum, dist, med, last, med_last


def _backward_group(geometry, opacities, features, gaussian_ids, group, res, cot, grads, height, width, cfg, depth):
    """Add one block group's contribution to the gradients of geometry, opacity, features."""
    tile_ids, starts, counts = group
    trans_final, zsum_final, last, med_last = res
    g_feat, g_trans, g_depth, g_dist, g_med = cot
    k = cfg.chunk_size
    n = geometry.shape[0]
    px, py, _ = _pixels(tile_ids, height, width, cfg, geometry.dtype)
    num_chunks = (jnp.max(last) + k - 1) // k

    def body(state):
        c, t_end, z_end, gt, gz, (d_geo, d_op, d_feat) = state
        gid, valid, offs = _gather(c, starts, counts, gaussian_ids, cfg)
        geo, op, feat = geometry[gid], opacities[gid], features[gid]
        alpha, _, z = _kernel(geo, op, px, py, cfg, depth)
        incl = valid[:, :, None] & (alpha >= cfg.alpha_min) & (offs[None, :, None] < last[:, None, :])
        hit = (offs[None, :, None] + 1) == med_last[:, None, :]
        a = jnp.where(incl, alpha, 0.0)
        t_in = t_end[:, None, :] / _cumulative(1.0 - a, jnp.multiply, 1.0, reverse=True)
        t0 = t_in[:, 0, :]
        z0 = z_end - jnp.sum(a * t_in * z, axis=1)

        def chunk(t0, z0, geo, op, feat):
            alpha, _, z = _kernel(geo, op, px, py, cfg, depth)
            state, contrib, _ = _terms(t0, z0, alpha, z, feat, incl, hit)
            return state, contrib

        _, vjp = jax.vjp(chunk, t0, z0, geo, op, feat)
        # The depth output is the final state Z (its cotangent enters through gz), not the
        # sum of the chunks' depth contributions.
        gt0, gz0, d_g, d_o, d_f = vjp(((gt, gz), (g_feat, jnp.zeros_like(g_depth), g_dist, g_med)))
        idx = jnp.where(valid, gid, n).reshape(-1)
        d_geo = d_geo.at[idx].add(d_g.reshape(-1, d_g.shape[-1]), mode="drop")
        d_op = d_op.at[idx].add(d_o.reshape(-1), mode="drop")
        d_feat = d_feat.at[idx].add(d_f.reshape(-1, d_f.shape[-1]), mode="drop")
        return c - 1, t0, z0, gt0, gz0, (d_geo, d_op, d_feat)

    init = (num_chunks - 1, trans_final, zsum_final, g_trans, g_depth, grads)
    return lax.while_loop(lambda s: s[0] >= 0, body, init)[-1]


@functools.cache
def _forward_fn(height: int, width: int, cfg: SplatConfig, depth: str) -> Callable:
    """All groups' forward pass: canvases ``(features, T, depth, distortion, median)`` and
    the per-group residuals, sequential under vmap."""

    @jax.named_scope("splat_composite")
    def forward(geometry, opacities, features, gaussian_ids, groups):
        def one(group):
            return _forward_group(geometry, opacities, features, gaussian_ids, group, height, width, cfg, depth)

        acc, trans, zsum, dist, med, last, med_last = lax.map(one, tuple(groups))
        tiles_y, tiles_x = cfg.tile_grid(height, width)
        where_tile = jnp.argsort(groups.tile_ids.reshape(-1), stable=True)[: tiles_y * tiles_x]
        p = acc.shape[-1]
        planes = jnp.stack([trans, zsum, dist, med], axis=2)  # [groups, group, 4, pix]
        feat = _to_canvas(acc.reshape(-1, acc.shape[2], p)[where_tile], height, width, cfg)
        t_c, z_c, d_c, m_c = jnp.moveaxis(_to_canvas(planes.reshape(-1, 4, p)[where_tile], height, width, cfg), -1, 0)
        return (feat, t_c, z_c, d_c, m_c), (trans, zsum, last, med_last)

    return sequential_over_batch(forward)


@functools.cache
def _backward_fn(height: int, width: int, cfg: SplatConfig, depth: str) -> Callable:
    """All groups' backward pass: ``(inputs, residuals, cotangents) -> (d_geometry,
    d_opacities, d_features)``, sequential under vmap."""

    @jax.named_scope("splat_composite")
    def backward(geometry, opacities, features, gaussian_ids, groups, res, cot):
        flat_ids = groups.tile_ids.reshape(-1)
        shape = res[0].shape  # [groups, group, pix]
        g_feat, *planes = cot
        gf = _from_canvas(g_feat, height, width, cfg)[flat_ids]
        gf = gf.reshape(shape[:-1] + gf.shape[1:])
        gp = _from_canvas(jnp.stack(planes, axis=-1), height, width, cfg)[flat_ids]
        gp = jnp.moveaxis(gp.reshape(shape[:-1] + gp.shape[1:]), 2, 0)  # [4, groups, group, pix]

        def step(grads, xs):
            group, group_res, group_cot = xs
            new = _backward_group(
                geometry,
                opacities,
                features,
                gaussian_ids,
                group,
                group_res,
                group_cot,
                grads,
                height,
                width,
                cfg,
                depth,
            )
            return new, None

        zero = _typed_zero(geometry.dtype, geometry, opacities, features, gaussian_ids, *res, *cot)
        zeros = tuple(jnp.zeros_like(x) + zero for x in (geometry, opacities, features))
        grads, _ = lax.scan(step, zeros, (tuple(groups), tuple(res), (gf, *gp)))
        return grads

    return sequential_over_batch(backward)


@functools.partial(jax.custom_vjp, nondiff_argnums=(0, 1, 2, 3))
def _composite(height, width, cfg, depth, geometry, opacities, features, gaussian_ids, groups):
    out, _ = _forward_fn(height, width, cfg, depth)(geometry, opacities, features, gaussian_ids, groups)
    return out


def _composite_fwd(height, width, cfg, depth, geometry, opacities, features, gaussian_ids, groups):
    out, res = _forward_fn(height, width, cfg, depth)(geometry, opacities, features, gaussian_ids, groups)
    return out, (geometry, opacities, features, gaussian_ids, groups, res)


def _composite_bwd(height, width, cfg, depth, saved, cotangents):
    geometry, opacities, features, gaussian_ids, groups, res = saved
    grads = _backward_fn(height, width, cfg, depth)(
        geometry, opacities, features, gaussian_ids, groups, res, cotangents
    )
    none_groups = _Groups(None, None, None)  # pyright: ignore[reportArgumentType] -- the integer tile lists have no cotangent: None
    return (*grads, None, none_groups)


_composite.defvjp(_composite_fwd, _composite_bwd)


def composite_surfels(
    means2d: Float[Array, "N 2"],
    ray_transforms: Float[Array, "N 3 3"],
    opacities: Float[Array, " N"],
    features: Float[Array, "N C"],
    bins: TileBins,
    height: int,
    width: int,
    cfg: SplatConfig = SplatConfig(),
    depth: str = "center",
) -> tuple[Float[Array, "H W C"], Float[Array, "H W"], Float[Array, "H W"], Float[Array, "H W"], Float[Array, "H W"]]:
    """Composite binned surfels front to back onto an ``height x width`` canvas.

    Returns ``(sum_i w_i f_i [H, W, C], T, sum_i w_i z_i, distortion, median depth)``, each
    ``[H, W]`` but the first; no background. ``depth`` is ``"center"`` or
    ``"intersection"`` (module docstring). Differentiable w.r.t. ``means2d``,
    ``ray_transforms``, ``opacities`` and ``features``.
    """
    if depth not in DEPTH_MODES:
        raise ValueError(f"depth must be one of {DEPTH_MODES}, got {depth!r}")
    geometry = jnp.concatenate([means2d, ray_transforms.reshape(-1, 9)], axis=-1)
    groups = _make_groups(bins, cfg)
    return _composite(height, width, cfg, depth, geometry, opacities, features, bins.gaussian_ids, groups)
