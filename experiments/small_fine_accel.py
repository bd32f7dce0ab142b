"""``small_fine.py``'s model (decoder token stride 4, width 128) on ``small_accel.py``'s recipe, 2,000 steps.

Run:  ACCEL_CONFIG=experiments/small_fine_accel.py bash experiments/accelerator_small.sh OUT

Does the wider model with the finer decoder, which met the one-scene overfit bars but trailed
``small`` through 12,000 CPU samples, overtake it once the data is plentiful? Compare its
held-out PSNR after 1,000 and 2,000 steps (16,000 and 32,000 samples, batch 16) with
``small_accel``'s 22.72 and 23.24 dB at the same steps (on its 4,000-step schedule).
"""

import os

from llrmpp_jax import config as C
from llrmpp_jax.experiment import load_experiment, replace


def get_config():
    """``small_accel.py`` with ``small_fine.py``'s model and a 2,000-step schedule inside 4 minutes."""
    here = os.path.dirname(os.path.abspath(__file__))
    accel = load_experiment(os.path.join(here, "small_accel.py"))
    fine = load_experiment(os.path.join(here, "small_fine.py"))
    stage = replace(accel.stages[0], steps=2_000)
    return replace(accel, name="small_fine_accel", model=fine.model, stages=(stage,), max_minutes=4.0)
