"""Small: a Long-LRM++ for procedural scenes that a 2-core CPU trains in hours (issue 13).

Run:  llrmpp train --config experiments/small.py --workdir runs/small     (resumes where it stopped)
Eval: llrmpp eval --config experiments/small.py --checkpoint runs/small --out runs/small/eval

64x64 procedural scenes, 8 input views -> 2 targets, batch 2, MSE only, lr 2e-3 (warmup 200,
cosine over 9k steps), held-out evaluation on 16 scenes every 2,000 steps, a checkpoint every
500 steps (a killed run resumes exactly). ``max_minutes`` is unset: stop it with Ctrl-C or
``timeout``; the next run continues from the newest checkpoint.

Why these numbers (experiments/README.md, "Learning at small scale"): on one scene, at equal
steps, neither a finer decoder (token stride 4), nor K=16 Gaussians per token, nor a finer
backbone (patch 4), nor colour mode learned faster than the demo's model; every variant sits
at 17.8-20 dB on its inputs after 400 steps while the demo's model keeps rising with steps (27.9 dB on its
inputs at 2,000). So the budget goes to steps: the demo's model and head (distance init 1.5
of max 3 units, scale init exp(-2.5)), 8 inputs as the paper's first stage, 64x64.

Cost on the shared 2-core box (load ~15; ``python experiments/bench_train.py --_case
small:0 --steps 3``, results/bench_train_small.json): 0.73 s per step, 58 s compile, but
1.9 s to ray-cast one batch of fresh procedural scenes on one thread: data generation, not
the model, bounds this run (~1 s per step with the 2 data workers) until scenes are cached.
"""

import os

from llrmpp_jax import config as C
from llrmpp_jax.experiment import load_experiment, replace


def get_config():
    """The demo's experiment with an all-attention backbone, LeCun-initialised head and
    decoder linears, 8 inputs and a 6k-step budget."""
    demo = load_experiment(os.path.join(os.path.dirname(os.path.abspath(__file__)), "demo.py"))
    m = demo.model
    model = C.replace(
        m, backbone=C.replace(m.backbone, pattern="{4T}x1"),
        head=C.replace(m.head, init_std=None), decoder=C.replace(m.decoder, init_std=None),
    )
    stage = replace(
        demo.stages[0], name="small", steps=6_000, num_inputs=8, warmup_steps=200, min_span=12, max_span=20,
    )
    data = replace(
        demo.data, procedural=replace(demo.data.procedural, num_frames=24), eval_span=16,
    )
    return replace(
        demo, name="small", model=model, stages=(stage,), data=data, log_every=20, eval_every=2000, checkpoint_every=1000, max_minutes=None,
    )
