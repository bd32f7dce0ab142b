"""``small.py``'s perceptual ``sharpen`` stage at batch 16, fine-tuned from ``pretrained:small`` on a lent accelerator.

Run:  ACCEL_INIT=pretrained:small ACCEL_CONFIG=experiments/small_accel_sharpen.py \
        bash experiments/accelerator_small.sh OUT     (carry .lpips and .whl; see that script)
      or here: llrmpp train --config experiments/small_accel_sharpen.py --init pretrained:small --workdir runs/as
Eval: llrmpp eval --config experiments/small_accel_sharpen.py --checkpoint runs/as --out runs/as/eval

Not yet run (no accelerator was lent since it was written). Why this run: on the CPU every
perceptual cycle (2,500-4,000 steps at batch 2: 5,000-8,000 samples, 70 minutes) lowered
held-out LPIPS by ~0.01 (0.429 -> 0.381 -> 0.373), the perceptual weight made no difference
(``small_resharpen_w2.py``), and what moved every metric on an accelerator was samples seen
(+0.8 dB from 16,000 to 32,000 in ``small.py``'s ``accel`` stage). Issue 13's bars are LPIPS
below the nearest view's 0.319 and input views >= 28 dB. At batch 16 and ~9 steps/s (the
``accel`` stage's rate on an H200, bound by its 14 sample processes; VGG16 on 64x64 targets
adds little there) 2,500 steps are ~40,000 samples in ~5 minutes, 5x a CPU cycle.

The stage is ``small.py``'s ``sharpen`` (MSE + 0.5 x perceptual, warmup 100, cosine) at batch 16,
with lr 5e-4 (``sharpen``'s rate; from converged weights, where the ``accel`` stage's 2e-3 would
undo them) and a 6-minute ``max_minutes`` per run (a checkpoint, then run again to finish).
"""

import os

from llrmpp_jax.experiment import load_experiment, replace


def get_config():
    """``small.py``'s ``sharpen`` at batch 16 for 2,500 steps (start: ``--init pretrained:small``), 7 minutes per run."""
    small = load_experiment(os.path.join(os.path.dirname(os.path.abspath(__file__)), "small.py"))
    stage = replace(small.stages[-1], name="accel_sharpen", steps=2_500, global_batch=16)
    return replace(small, name="small_accel_sharpen", stages=(stage,), max_minutes=7.0, eval_every=500,
                   checkpoint_every=500, keep_checkpoints=1)
