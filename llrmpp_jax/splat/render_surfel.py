"""The 2DGS core of :func:`~llrmpp_jax.splat.rasterize` (``primitive="2dgs"``): surfel
projection (:mod:`.surfel`) -> the shared tile binning (:mod:`.binning`, boxes from the
surfels' extents) -> the surfel compositor (:mod:`.composite_surfel`).

The camera-frame normals ride as three extra feature channels of the one composite.
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp

from llrmpp_jax.array_typing import Array, Float, Int
from llrmpp_jax.splat.binning import TileBins, bin_gaussians, intersection_counts
from llrmpp_jax.splat.composite_surfel import composite_surfels
from llrmpp_jax.splat.config import SplatConfig
from llrmpp_jax.splat.surfel import ProjectedSurfels, as_binnable, project_surfels


class SurfelCanvas(NamedTuple):
    """S opacity copies of one render (leading S axis on every canvas)."""

    features: Float[Array, "S H W F"]
    transmittance: Float[Array, "S H W"]
    depth: Float[Array, "S H W"]  # accumulated sum_i w_i z_i
    normals: Float[Array, "S H W 3"]  # sum_i w_i n_i, camera frame
    median_depth: Float[Array, "S H W"]
    distortion: Float[Array, "S H W"]
    radii: Int[Array, " N"]
    bins: TileBins


def render_surfel_copies(
    means: Float[Array, "N 3"],
    quats: Float[Array, "N 4"],
    scales: Float[Array, "N 2"],
    opacities: Float[Array, "S N"],
    features: Float[Array, "N F"],
    c2w: Float[Array, "4 4"],
    intrinsics: Float[Array, " 4"],
    height: int,
    width: int,
    capacity: int,
    cfg: SplatConfig,
    depth: str,
    keep: jax.Array,
) -> SurfelCanvas:
    """Render S opacity copies of N sanitised surfels (``keep`` False drops one) sharing
    one projection and one binning."""
    f = features.shape[1]
    most = jnp.max(opacities, axis=0)
    with jax.named_scope("splat_project"):
        proj = project_surfels(means, quats, scales, most, c2w, intrinsics, height, width, cfg, keep=keep)
    with jax.named_scope("splat_bin"):
        boxes = (proj.extents[:, 0], proj.extents[:, 1])
        bins = bin_gaussians(as_binnable(proj), height, width, capacity, cfg, extents=boxes)
    feats_n = jnp.concatenate([features, proj.normals], axis=-1)

    def one(op):
        return composite_surfels(proj.means2d, proj.ray_transforms, op, feats_n, bins, height, width, cfg, depth)

    canvas, trans, zsum, dist, med = jax.vmap(one)(opacities)
    return SurfelCanvas(canvas[..., :f], trans, zsum, canvas[..., f:], med, dist, proj.radii, bins)


def surfel_counts(surfels: ProjectedSurfels, height: int, width: int, cfg: SplatConfig) -> Int[Array, " N"]:
    """Compositor blocks each projected surfel enters (what its render's binning fills)."""
    ext = (surfels.extents[:, 0], surfels.extents[:, 1])
    return intersection_counts(as_binnable(surfels), height, width, cfg, extents=ext)
