"""``small.py``'s perceptual ``sharpen`` stage at batch 16, fine-tuned from ``pretrained:small`` on a lent accelerator.

Run:  ACCEL_INIT=pretrained:small ACCEL_CONFIG=experiments/small_accel_sharpen.py \
        bash experiments/accelerator_small.sh OUT     (carry .lpips and .whl; see that script)
      or here: llrmpp train --config experiments/small_accel_sharpen.py --init pretrained:small --workdir runs/as
Eval: llrmpp eval --config experiments/small_accel_sharpen.py --checkpoint runs/as --out runs/as/eval

Run twice on a lent H200 (session of 2026-11-27), the second time from the first's checkpoint
(``WORKDIR=/tmp/small_accel2 ACCEL_INIT=/tmp/small_accel``, the same warm machine), and shipped
as ``pretrained:small`` after each: ~9.3 steps/s (~150 samples/s), ~6 minutes per run with
compile (~48 s) and five held-out evaluations (~28 s for the first, a few seconds each after).
``llrmpp eval`` on the 16 held-out scenes, PSNR / SSIM / LPIPS / input views re-rendered:

| weights | PSNR | SSIM | LPIPS | input views | steps in all |
|---|---|---|---|---|---|
| start: ``small_resharpen_long.py``'s end | 24.42 | 0.643 | 0.330 | 25.69 | 33,500 |
| first run | 24.66 | 0.661 | 0.297 | 25.95 | 36,000 |
| second run (shipped) | **24.85** | **0.675** | **0.282** | **26.14** | 38,500 |

Why this run: on the CPU every perceptual cycle (2,500-5,000 steps at batch 2: 5,000-10,000
samples, 40-95 minutes) lowered held-out LPIPS by 0.003-0.010, the perceptual weight made no
difference (``small_resharpen_w2.py``), and what moved every metric on an accelerator was
samples seen (+0.8 dB from 16,000 to 32,000 in ``small.py``'s ``accel`` stage). Each run here is
40,000 samples: LPIPS -0.033, then -0.015, about the CPU's gain per sample in 1/16 of the time.

The stage is ``small.py``'s ``sharpen`` (MSE + 0.5 x perceptual, warmup 100, cosine) at batch 16,
with lr 5e-4 (``sharpen``'s rate; from converged weights, where the ``accel`` stage's 2e-3 would
undo them), a 7-minute ``max_minutes`` per run (a checkpoint, then run again to finish) and one
checkpoint kept (the packed workdir, 14.4 MB, is one file under a lease's 16 MiB limit).
"""

from dataclasses import replace

from llrmpp_jax.experiment import load_experiment


def get_config():
    """``small.py``'s ``sharpen`` at batch 16 for 2,500 steps (start: ``--init pretrained:small``), 7 minutes
    per run."""
    small = load_experiment("small")
    stage = replace(small.stages[-1], name="accel_sharpen", steps=2_500, global_batch=16)
    return replace(
        small,
        name="small_accel_sharpen",
        stages=(stage,),
        max_minutes=7.0,
        eval_every=500,
        checkpoint_every=500,
        keep_checkpoints=1,
    )
