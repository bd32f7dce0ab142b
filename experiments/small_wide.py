"""Small, twice as wide: does width carry the detail the shipped ``small`` model blurs away?

Run:  nice -n 10 llrmpp train --config experiments/small_wide.py --workdir ~/runs/small_wide   (resumes)
Eval: llrmpp eval --config experiments/small_wide.py --checkpoint ~/runs/small_wide --out ~/runs/small_wide/eval

``experiments/small_cpu.py`` (data, stages, schedule, losses, evaluation) with one change: the
backbone and decoder widths 64 -> 128 (head_dim 16 kept, so 8 heads instead of 4). At
width 64 a token carries an 8x8 patch (192 colour values plus its rays) in 64 numbers and
the decoder expands 64 numbers back into 192; every other lever tried at that width stops
at ~18.5 dB on the overfit scene's held-out views and LPIPS 0.53 across scenes
(experiments/README.md). Compare its held-out evaluations at steps 2,000 / 4,000 / 6,000
with ``small``'s (20.30 / 21.82 / 22.15 dB). On this 2-core CPU it runs ~1.75 steps/s
(``small``: ~2.4), data included.
"""

import os

from llrmpp_jax import config as C
from llrmpp_jax.experiment import load_experiment, replace


def get_config():
    """``small_cpu.py`` with backbone and decoder width 128."""
    small = load_experiment(os.path.join(os.path.dirname(os.path.abspath(__file__)), "small_cpu.py"))
    m = small.model
    # Measured against small_cpu.py's head as it was then (Gaussians started at the patch centre).
    m = C.replace(m, head=C.replace(m.head, anchors="centre", scale_bias=-2.5))
    model = C.replace(m, backbone=C.replace(m.backbone, dims=(128,)), decoder=C.replace(m.decoder, dim=128))
    return replace(small, name="small_wide", model=model)
