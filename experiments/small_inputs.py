"""``small_resharpen.py`` with the input frames drawn as targets at weight 1.0 (its one change).

Run:  llrmpp train --config experiments/small_inputs.py --init pretrained:small --workdir ~/runs/inputs

Long-LRM++ draws a training target among a window's frames with weight 0.1 for the input
frames and 1 for the rest (``StageConfig.input_weight``): with 8 inputs in a window of 24
frames, ~5% of the targets are input views. Issue 13 asks the model to re-render its input
views at >= 28 dB, and ``pretrained:small`` does so at 25.21 dB, close to the views' 4x4 block
means. At weight 1.0 a third of the targets are input views. This run asks what that buys the
input views and what it costs the novel ones, against ``small_resharpen.py`` from the same
weights, same data and steps, on the other core.
"""

import os

from llrmpp_jax.experiment import load_experiment, replace


def get_config():
    """``small_resharpen.py`` with ``input_weight`` 1.0."""
    base = load_experiment(os.path.join(os.path.dirname(os.path.abspath(__file__)), "small_resharpen.py"))
    return replace(base, name="small_inputs", stages=(replace(base.stages[0], name="inputs", input_weight=1.0),))
