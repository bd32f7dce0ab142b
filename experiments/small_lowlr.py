"""``small_resharpen.py`` at a quarter of its learning rate, 5e-5 (its one change).

Run:  llrmpp train --config experiments/small_lowlr.py --init pretrained:small --workdir ~/runs/lowlr

Every ``small_resharpen.py`` cycle from the converged model first loses ground (held-out PSNR
-0.2 dB and LPIPS up at step 500 of 2,500, at 2e-4) and gains only as the cosine rate decays:
the batch-2 gradient noise at the peak rate undoes part of what the previous cycle reached.
This run asks whether a rate four times lower keeps the gains without the dip, against a
fourth ``small_resharpen.py`` cycle from the same weights on the other core (same data, steps
and evaluations).
"""

import os

from llrmpp_jax.experiment import load_experiment, replace


def get_config():
    """``small_resharpen.py`` with the peak learning rate 5e-5."""
    base = load_experiment(os.path.join(os.path.dirname(os.path.abspath(__file__)), "small_resharpen.py"))
    return replace(base, name="small_lowlr", stages=(replace(base.stages[0], name="lowlr", lr=5e-5),))
