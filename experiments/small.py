"""Small: the shipped Long-LRM++ for procedural scenes (``pretrained:small``).

Run:  llrmpp train --config experiments/small.py --workdir runs/small     (resumes where it stopped)
      (on a lent accelerator: ``bash experiments/accelerator_small.sh OUT``, small_accel.py)
Eval: llrmpp eval --config experiments/small.py --checkpoint runs/small --out runs/small/eval
Ship: python experiments/ship_weights.py --workdir runs/small --config experiments/small.py --name small

64x64 procedural scenes of 24 frames, 8 input views -> 2 targets, one stage, ``accel``: 2,000
steps of MSE at batch 16 (lr 2e-3, warmup 200, cosine), its samples built by 14 spawned
processes (``DataConfig.worker_processes``). Trained on one H200 of a lease: 3.6 minutes at
~9.2 steps/s (~150 samples/s), 24.12 dB held out (LPIPS 0.429, input views 25.01).

The network is ``small_fine.py``'s: the CPU recipe's (``small_cpu.py``) with the decoder's
token stride 8 -> 4 and the backbone and decoder widths 64 -> 128 (1.3M parameters). Through
12,000 CPU samples it trailed the width-64 model; with data from an accelerator it leads: 23.29
/ 24.12 dB after 16,000 / 32,000 samples against the width-64 model's 22.72 / 23.24 at the same
samples (and 23.70 after 64,000; experiments/README.md, "`small.py`").

Otherwise the model is the demo's, with its three departures from Long-LRM's recipe (the
Gaussians' grid start, a ``{4T}x1`` backbone, LeCun-normal head and decoder init), each with its
evidence in ``small_cpu.py``'s docstring.
"""

import os

from llrmpp_jax.experiment import load_experiment, replace


def get_config():
    """``small_fine.py`` (``small_cpu.py`` at width 128, stride 4): its first stage as 2k steps at batch 16, data from 14 processes."""
    fine = load_experiment(os.path.join(os.path.dirname(os.path.abspath(__file__)), "small_fine.py"))
    accel = replace(fine.stages[0], name="accel", steps=2_000, global_batch=16)
    data = replace(fine.data, workers=14, worker_processes=True)
    return replace(fine, name="small", stages=(accel,), data=data, eval_every=1000)
