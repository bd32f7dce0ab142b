"""``small_resharpen.py`` over 5,000 steps instead of 2,500 (its one change): one long cycle or two short ones?

Run:  llrmpp train --config experiments/small_resharpen_long.py --init pretrained:small --workdir ~/runs/resharpen_long

Each ``small_resharpen.py`` cycle loses ground while its rate is high (held-out PSNR -0.2 dB at
step 500) and gains as the cosine decays, about 0.0035 LPIPS per cycle over the last six. This
run asks whether one cosine twice as long, from the same peak, gains more than two cycles in
the same steps: the tenth fine-tuning of ``pretrained:small``, from the ninth's weights.
"""

import os

from llrmpp_jax.experiment import load_experiment, replace


def get_config():
    """``small_resharpen.py`` with 5,000 steps."""
    base = load_experiment(os.path.join(os.path.dirname(os.path.abspath(__file__)), "small_resharpen.py"))
    return replace(base, name="small_resharpen_long",
                   stages=(replace(base.stages[0], name="resharpen_long", steps=5_000),))
