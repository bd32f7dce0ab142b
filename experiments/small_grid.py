"""Small, with each token's Gaussians starting on a sub-grid of its patch: does a canvas that
starts sharp let ``small`` carry detail finer than a patch?

Run:  nice -n 10 llrmpp train --config experiments/small_grid.py --workdir ~/runs/small_grid   (resumes)
Eval: llrmpp eval --config experiments/small_grid.py --checkpoint ~/runs/small_grid --out ~/runs/small_grid/eval

``experiments/small.py`` with one change to the Gaussian head's initialisation:
``anchors="grid"`` (the K = 4 Gaussians of a token start on the centres of a 2 x 2 split of its
patch, on-axis, isotropic, at ``max_dist / 2``; ``gaussians.head_kernel_init``) and
``scale_bias`` -2.5 -> -3.0, so that a Gaussian 1.5 units out covers about one cell (sigma
~1 canvas pixel at the procedural cameras' focal length, 64 px on the image, 32 on the canvas).
``small`` starts its Gaussians all at the patch centre with drawn offsets, scales and
rotations, and sigma ~1.75 canvas pixels: a patch's Gaussians cover each other.

Why (experiments/README.md, "Fourth round"): ``pretrained:small`` re-renders its input views
at the 8 x 8 block mean's PSNR, with or without the other views' Gaussians; on the
single-view re-render test the grid start reaches 26.5 dB in 2,000 steps against 24.7.
Compare its held-out evaluations with ``small``'s (20.30 / 21.82 / 22.15 dB at 2,000 /
4,000 / 6,000 steps; input views 20.76 / 22.39 / 22.77).
"""

import os

from llrmpp_jax import config as C
from llrmpp_jax.experiment import load_experiment, replace


def get_config():
    """``small.py`` with the grid start of its Gaussians."""
    small = load_experiment(os.path.join(os.path.dirname(os.path.abspath(__file__)), "small.py"))
    m = small.model
    return replace(small, name="small_grid",
                   model=C.replace(m, head=C.replace(m.head, anchors="grid", scale_bias=-3.0)))
