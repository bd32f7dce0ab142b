"""Small on one accelerator: ``small.py``'s model and data at batch 16, MSE only, from scratch.

Run:  llrmpp train --config experiments/small_accel.py --workdir runs/small_accel
      (on the lent H200: ``bash experiments/accelerator_small.sh OUT``)

A probe of what limits ``pretrained:small`` (issue 13): steps and data, or the model at this
size. ``small.py``'s MSE stage saw 12,000 samples (6,000 steps of 2) on the 2-core CPU, and
its held-out PSNR on 16 scenes was 21.74 / 22.61 / 23.00 dB after 4,000 / 8,000 / 12,000 of
them. Here 16 samples per step, built by 14 spawned processes (``DataConfig.worker_processes``:
the NumPy ray caster holds the GIL, so threads stay near ~21 samples/s on any host), lr 2e-3
(as ``small``), 4,000 steps (64,000 samples) on a cosine schedule, stopped by ``max_minutes``
on a slower host; held-out PSNR on the same 16 scenes every 1,000 steps.
"""

import os

from llrmpp_jax.experiment import load_experiment, replace


def get_config():
    """``small.py``'s first stage at batch 16 for 4,000 steps, data from 14 worker processes."""
    small = load_experiment(os.path.join(os.path.dirname(os.path.abspath(__file__)), "small.py"))
    stage = replace(small.stages[0], name="accel", global_batch=16, steps=4_000)
    data = replace(small.data, workers=14, worker_processes=True)
    return replace(small, name="small_accel", stages=(stage,), data=data, eval_every=1000,
                   checkpoint_every=1000, max_minutes=6.0)
