"""Jitted sort-and-composite splatter of feature Gaussians (gsplat "classic" semantics).

Pipeline: :mod:`.projection` (EWA) -> :mod:`.binning` (tile lists in a static-capacity
buffer) -> :mod:`.composite` (front-to-back, custom VJP). :mod:`.render` holds the entry
point :func:`rasterize` (gsplat's render modes: "F" features, "RGB" SH colour, "D" / "ED"
depth, "F+ED", "RGB+ED"; ``primitive="2dgs"`` for 2D Gaussians) and :func:`fit_capacity`,
which sizes its buffer from the cameras; :mod:`.sh` the colour mode's spherical harmonics,
:mod:`.reference` a brute-force O(N x pixels) renderer used as oracle and benchmark baseline.
2DGS (surfels): :mod:`.surfel` (ray-transform projection) -> the same binning ->
:mod:`.composite_surfel` (features, normals, depth, median depth, distortion), wired by
:mod:`.render_surfel`; :mod:`.reference_2dgs` is its brute-force oracle.
"""

from llrmpp_jax.splat.config import SplatConfig
from llrmpp_jax.splat.render import RENDER_MODES, SplatOutput, SplatStats, fit_capacity, rasterize

__all__ = ["RENDER_MODES", "SplatConfig", "SplatOutput", "SplatStats", "fit_capacity", "rasterize"]
