"""``small_resharpen.py`` over 5,000 steps instead of 2,500 (its one change): one long cycle or two short ones?

Run:  llrmpp train --config experiments/small_resharpen_long.py --init pretrained:small --workdir ~/runs/resharpen_long

Each ``small_resharpen.py`` cycle loses ground while its rate is high (held-out PSNR -0.2 dB at
step 500) and gains as the cosine decays, about 0.0035 LPIPS per cycle over the last six. This
run asks whether one cosine twice as long, from the same peak, gains more than two cycles in
the same steps: the tenth fine-tuning of ``pretrained:small``, from the ninth's weights.

It gains more than two, about as much as three. From the 28,500-step model (24.39 dB, SSIM
0.640, LPIPS 0.340, input views 25.63), both cores, 95 minutes (a test suite and the demo
shared them for 40): held-out PSNR (input views) at steps 500-5,000 24.19 (25.38), 23.97
(25.18), 24.20 (25.43), 24.11 (25.25), 24.27 (25.48), 24.42 (25.61), 24.40 (25.64), 24.42
(25.67), 24.39 (25.68), 24.42 (25.69); ``llrmpp eval`` at 5,000 **24.42 dB, SSIM 0.643, LPIPS
0.330, input views 25.69** (33,500 steps; shipped as ``pretrained:small``, then fine-tuned twice
by ``small_accel_sharpen.py`` on a lent H200, each run gaining more than this). LPIPS -0.010, where
the last six 2,500-step cycles gained 0.003-0.004 each. The dip is as deep (23.97 at step
1,000) and paid once instead of twice; the held-out PSNR passes the start by step 3,000.
"""

import os

from llrmpp_jax.experiment import load_experiment, replace


def get_config():
    """``small_resharpen.py`` with 5,000 steps."""
    base = load_experiment(os.path.join(os.path.dirname(os.path.abspath(__file__)), "small_resharpen.py"))
    return replace(base, name="small_resharpen_long",
                   stages=(replace(base.stages[0], name="resharpen_long", steps=5_000),))
