"""``small_resharpen.py`` with the perceptual weight 0.5 -> 2.0 (its one change).

Run:  llrmpp train --config experiments/small_resharpen_w2.py --init pretrained:small --workdir ~/runs/resharpen_w2

The perceptual term already makes ~94% of the loss's value at 0.5 (0.5 x ~0.17 against an
MSE of ~0.005 late in ``small.py``'s ``sharpen``), but Adam follows the gradient's direction,
not the loss's size: this run asks whether moving that direction further towards the
perceptual term lowers held-out LPIPS, and what it costs in PSNR. The paper's weight is 0.5.

It does neither: same data, same steps, on the other core beside ``small_resharpen.py``,
held-out PSNR / SSIM / LPIPS / input views at steps 500 / 1,000 / 1,500 / 2,000 / 2,500 were
24.01 / 0.610 / 0.387 / 24.99, 23.98 / 0.604 / 0.387 / 25.04, 24.03 / 0.611 / 0.382 / 25.10,
24.10 / 0.616 / 0.373 / 25.14 and 24.15 / 0.617 / 0.373 / 25.20, within 0.04 dB and 0.004
LPIPS of the weight-0.5 run at every evaluation. The perceptual term already steers the
update; what keeps LPIPS at 0.37 is not its weight.
"""

import os

from llrmpp_jax.experiment import load_experiment, replace


def get_config():
    """``small_resharpen.py`` at perceptual weight 2.0."""
    base = load_experiment(os.path.join(os.path.dirname(os.path.abspath(__file__)), "small_resharpen.py"))
    return replace(base, name="small_resharpen_w2",
                   stages=(replace(base.stages[0], name="resharpen_w2", perceptual_weight=2.0),))
