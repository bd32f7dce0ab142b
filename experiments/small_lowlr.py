"""``small_resharpen.py`` at a quarter of its learning rate, 5e-5 (its one change).

Run:  llrmpp train --config experiments/small_lowlr.py --init pretrained:small --workdir ~/runs/lowlr

Every ``small_resharpen.py`` cycle from the converged model first loses ground (held-out PSNR
-0.2 dB and LPIPS up at step 500 of 2,500, at 2e-4) and gains only as the cosine rate decays:
the batch-2 gradient noise at the peak rate undoes part of what the previous cycle reached.
This run asks whether a rate four times lower keeps the gains without the dip, against a
fourth ``small_resharpen.py`` cycle from the same weights on the other core (same data, steps
and evaluations).

Measured (held-out PSNR with input views in brackets, from the training's evaluations at steps
500-2,500; the fourth ``small_resharpen.py`` cycle beside it after the slash; both from the
13,500-step ``pretrained:small``, 24.23 (25.42), LPIPS 0.361; 68 minutes each, one core each):
24.24 (25.43) / 24.05 (25.18), 24.20 (25.40) / 23.96 (25.17), 24.23 (25.41) / 24.20 (25.37),
24.22 (25.42) / 24.18 (25.40), 24.24 (25.44) / 24.25 (25.45). ``llrmpp eval`` at 2,500: 24.24
dB, SSIM 0.627, LPIPS 0.361, against 24.25 / 0.628 / **0.357**. At 5e-5 there is no dip, and no
gain either: the model stays where it started. The peak rate's noise is what moves LPIPS (the
2e-4 cycle was shipped); the paper-like dip-and-recover schedule stays.
"""

import os

from llrmpp_jax.experiment import load_experiment, replace


def get_config():
    """``small_resharpen.py`` with the peak learning rate 5e-5."""
    base = load_experiment(os.path.join(os.path.dirname(os.path.abspath(__file__)), "small_resharpen.py"))
    return replace(base, name="small_lowlr", stages=(replace(base.stages[0], name="lowlr", lr=5e-5),))
