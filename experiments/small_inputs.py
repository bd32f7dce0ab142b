"""``small_resharpen.py`` with the input frames drawn as targets at weight 1.0 (its one change).

Run:  llrmpp train --config experiments/small_inputs.py --init pretrained:small --workdir ~/runs/inputs

Long-LRM++ draws a training target among a window's frames with weight 0.1 for the input
frames and 1 for the rest (``StageConfig.input_weight``): with 8 inputs in a window of 24
frames, ~5% of the targets are input views. Issue 13 asks the model to re-render its input
views at >= 28 dB, and ``pretrained:small`` does so at 25.21 dB, close to the views' 4x4 block
means. At weight 1.0 a third of the targets are input views. This run asks what that buys the
input views and what it costs the novel ones, against ``small_resharpen.py`` from the same
weights, same data and steps, on the other core.

Measured (held-out PSNR with input views in brackets, from the training's evaluations at steps
500-2,500; the ``small_resharpen.py`` run beside it after the slash): 23.90 (25.13) / 24.00
(25.04), 23.89 (25.26) / 23.99 (25.12), 24.01 (25.42) / 24.10 (25.22), 24.09 (25.50) / 24.16
(25.28), 24.11 (25.54) / 24.21 (25.34). ``llrmpp eval`` at 2,500: 24.11 dB, SSIM 0.619, LPIPS
0.366, input views 25.54, against 24.21 / 0.623 / 0.366 / 25.34. Six times the input views among
the targets buys them 0.2 dB and costs the novel views 0.1: how often the inputs are targets is
not what keeps them at 25 dB, and the paper's 0.1 stays.
"""

import os

from llrmpp_jax.experiment import load_experiment, replace


def get_config():
    """``small_resharpen.py`` with ``input_weight`` 1.0."""
    base = load_experiment(os.path.join(os.path.dirname(os.path.abspath(__file__)), "small_resharpen.py"))
    return replace(base, name="small_inputs", stages=(replace(base.stages[0], name="inputs", input_weight=1.0),))
