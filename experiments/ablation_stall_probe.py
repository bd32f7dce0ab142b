"""Stalled-seed probe (notebooks/README.md, "Stalled seeds"): train one ablation row at the
cpu scale for the given seeds, keeping snapshots, and record per-step loss and gradient norm
plus Gaussian statistics (opacity, log-scale, distance to the inputs) at each snapshot and
the held-out scores.

Run (from the repository root; one core, ~5 min per seed on the 2-core development box):
    taskset -c 1 python experiments/ablation_stall_probe.py 16 32 0.5 LLGGG 1 1 \
        experiments/results/ablations/stall/s1_guard.json         # K F canvas blocks S seeds out
    SPIKE_FACTOR=none ...  s1.json                                # without the spike guard
    LR=1e-3 WARMUP=100 ...                                        # another peak rate / warmup
    taskset -c 1 python experiments/ablation_stall_probe.py depth noaux 3,6 OUT.json
                             # Table 7's Long-LRM++ rows (aux: with the auxiliary depth losses)
"""

import dataclasses
import json
import os
import sys
from dataclasses import replace

import jax
import numpy as np

from llrmpp_jax import ablation as A
from llrmpp_jax.model import reconstruct

depth = sys.argv[1] == "depth"
if depth:  # Table 7's scale and base model (RGB + depth heads), as notebooks/table7_depth_losses.py
    aux, seeds_arg, out = sys.argv[2], sys.argv[3], sys.argv[4]
    if aux not in ("aux", "noaux"):
        raise SystemExit(f"depth rows: 'aux' or 'noaux', got {aux!r}")
    steps = int(os.environ.get("STEPS", 800))
    scale = A.make_scale("cpu", paper_views=8, depth=True, cpu_steps=steps)
else:
    k, f, canvas, blocks, S = int(sys.argv[1]), int(sys.argv[2]), float(sys.argv[3]), sys.argv[4], int(sys.argv[5])
    seeds_arg, out = sys.argv[6], sys.argv[7]
    steps = int(os.environ.get("STEPS", 400))
    scale = A.make_scale("cpu", paper_views=4, cpu_steps=steps)
seeds = [int(s) for s in seeds_arg.split(",")]
spike = os.environ.get("SPIKE_FACTOR")
if spike:
    scale = dataclasses.replace(scale, spike_factor=None if spike == "none" else float(spike))
if os.environ.get("LR"):
    scale = dataclasses.replace(scale, lr=float(os.environ["LR"]))
if os.environ.get("WARMUP"):
    scale = dataclasses.replace(scale, warmup=int(os.environ["WARMUP"]))
if depth:
    cfg = scale.base
    variant = A.Variant({}, lambda b: cfg, {}, **({} if aux == "aux" else dict(grad_weight=0.0, normal_weight=0.0)))  # pyright: ignore[reportArgumentType] -- the dict's floats go to the weight fields, not to chosen
else:
    cfg = replace(
        scale.base,
        head=replace(scale.base.head, gaussians_per_token=k, feature_dim=f),
        decoder=replace(
            scale.base.decoder, blocks=blocks, dim=scale.width(256), canvas_ratio=round(1 / canvas), partitions=S
        ),
    )
    variant = A.Variant({}, lambda b: cfg, {})
held_out = A.held_out_samples(cfg, scale)
samples = held_out[:4]  # the Gaussian statistics use the first four
snaps = sorted({0, 10, 25, 50, 100, 200, steps // 2, steps})

recon = jax.jit(lambda p, s: reconstruct(p, cfg, s["input_images"], s["input_c2w"], s["input_intrinsics"]))


def stats(params):
    rows = []
    for s in samples:
        g = recon(params, {k: v[None] for k, v in s.items()})
        o = np.asarray(g.opacities).ravel()
        sc = np.log(np.asarray(g.scales)).ravel()
        cam = np.asarray(s["input_c2w"])[:, :3, 3]
        d = np.linalg.norm(np.asarray(g.means)[0][:, None] - cam[None], axis=-1).min(1)
        feat = np.linalg.norm(np.asarray(g.features)[0], axis=-1)
        rows.append(
            dict(
                op_mean=o.mean(),
                op_lt01=(o < 0.01).mean(),
                op_gt09=(o > 0.9).mean(),
                logscale_mean=sc.mean(),
                logscale_sd=sc.std(),
                dist_mean=d.mean(),
                dist_gt9=(d > 9.0).mean(),
                feat_norm=feat.mean(),
            )
        )
    return {k: float(np.mean([r[k] for r in rows])) for k in rows[0]}


res = {}
for seed in seeds:
    t = A.train(cfg, scale, variant, seed=seed, snapshots=snaps)
    t.snapshots[0] = A.init_model(cfg, scale, seed)
    ev = A.row_scores(t.params, cfg, held_out)
    res[seed] = dict(
        losses=t.losses.tolist(),
        grad_norms=t.grad_norms.tolist(),
        seconds=t.seconds,
        snap={str(k): stats(v) for k, v in sorted(t.snapshots.items())},
        eval=ev,
    )
    print(seed, f"final loss {np.mean(t.losses[-20:]):.4f}", res[seed]["eval"], flush=True)
    json.dump(res, open(out, "w"))
