"""Jitted sort-and-composite splatter of feature Gaussians (gsplat "classic" semantics).

Pipeline: :mod:`.projection` (EWA) -> :mod:`.binning` (tile lists in a static-capacity
buffer) -> :mod:`.composite` (front-to-back, custom VJP). :mod:`.render` holds the entry
points, :mod:`.sh` the colour mode's spherical harmonics, :mod:`.reference` a brute-force
O(N x pixels) renderer used as oracle and benchmark baseline.
"""

from llrmpp_jax.splat.config import SplatConfig
from llrmpp_jax.splat.render import (
    SplatOutput,
    SplatStats,
    count_intersections,
    expected_depth,
    fitted_capacity,
    render_feature_copies,
    render_features,
    render_sh,
)

__all__ = [
    "SplatConfig",
    "SplatOutput",
    "SplatStats",
    "count_intersections",
    "expected_depth",
    "fitted_capacity",
    "render_feature_copies",
    "render_features",
    "render_sh",
]
