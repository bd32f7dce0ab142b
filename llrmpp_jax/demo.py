"""``llrmpp demo``: the project's two jobs on procedural scenes, in about ten minutes on a CPU.

1. **Reconstruct** (:func:`reconstruct_with_shipped`): the shipped model (``pretrained:small``,
   trained with the ``small`` recipe) on its held-out procedural scenes (8 inputs -> 2
   targets): the model beside both baselines (mean colour, nearest input view) with the
   diagnostics, picture grids (inputs, inputs re-rendered, per target the prediction, its
   error, the nearest view and the Gaussians' depth); then the first 4 scenes refined for 10
   steps (the paper's Table 1) against their inputs (:mod:`llrmpp_jax.refine`), held-out PSNR
   and LPIPS and input-view PSNR before and after.
2. **Train** (:func:`train_from_scratch`): the tiny demo model (the ``demo`` recipe) from
   random weights for a few minutes: the training loss and the held-out PSNR at each
   evaluation, and its picture grids.

Each part writes its pictures and a ``metrics.json`` under ``out/shipped`` and ``out/scratch``.
"""

from __future__ import annotations

import json
import os
import shutil
import time
from dataclasses import replace

import jax
import numpy as np

from llrmpp_jax.data.image_io import write_image
from llrmpp_jax.evaluate import evaluate, scene_picture, summary_table
from llrmpp_jax.experiment import load_experiment
from llrmpp_jax.experiment_data import eval_samples
from llrmpp_jax.metrics import load_lpips_params
from llrmpp_jax.pretrained import load_pretrained
from llrmpp_jax.trainer import train


def reconstruct_with_shipped(
    out: str, name: str = "small", pictures: int = 4, refine_scenes: int = 4, refine_steps: int = 10
) -> dict:
    """Part 1 (module docstring). Returns ``{"summary", "per_scene", "refine"}``, ``refine``
    holding the first ``refine_scenes`` scenes' mean ``model`` and ``refined_<steps>`` rows
    (:func:`evaluate` with ``refine_steps``); writes ``out/grid_*.png`` and ``out/metrics.json``."""
    os.makedirs(out, exist_ok=True)
    exp = load_experiment(name)
    params, cfg = load_pretrained(name, exp.model)
    samples, names = eval_samples(exp, exp.stages[-1])
    lpips_params = load_lpips_params()
    rows, summary, _ = evaluate(params, cfg, samples, lpips_params, names)
    for i in range(min(pictures, len(samples))):
        write_image(os.path.join(out, f"grid_{i}.png"), scene_picture(params, cfg, samples[i]))
    _, refined, _ = evaluate(
        params, cfg, samples[:refine_scenes], lpips_params, names[:refine_scenes], refine_steps=refine_steps
    )
    report = {
        "summary": summary,
        "per_scene": rows,
        "refine": {
            "scenes": min(refine_scenes, len(samples)),
            "steps": refine_steps,
            "model": refined["model"],
            "refined": refined[f"refined_{refine_steps}"],
        },
    }
    with open(os.path.join(out, "metrics.json"), "w") as f:
        json.dump(report, f, indent=1)
    return report


def train_from_scratch(out: str, steps: int | None = None, minutes: float | None = None) -> dict:
    """Part 2 (module docstring): the ``demo`` recipe (``steps`` / ``minutes`` override its
    budget). Returns ``{"summary", "evals", "loss_curve", "train_seconds"}``; writes
    ``out/grid_*.png``, ``out/metrics.json`` and the training workdir's files under ``out``.
    ``out`` is emptied first: the trainer resumes a workdir's checkpoints, so a second
    ``make demo`` would otherwise "train" no step and show no loss curve."""
    shutil.rmtree(out, ignore_errors=True)
    exp = load_experiment("demo")
    if steps:
        exp = replace(exp, stages=tuple(replace(s, steps=steps) for s in exp.stages))
    t0 = time.time()
    result = train(exp, out, max_minutes=minutes)
    t_train = time.time() - t0
    samples, names = eval_samples(exp, exp.stages[-1])
    _, summary, _ = evaluate(result["params"], exp.model, samples, load_lpips_params(), names)
    params = jax.device_get(result["params"])
    for i in range(min(4, len(samples))):
        write_image(os.path.join(out, f"grid_{i}.png"), scene_picture(params, exp.model, samples[i]))
    report = {
        "summary": summary,
        "evals": result.get("evals", []),
        "train_seconds": t_train,
        "loss_curve": [(h["step"], h["loss"]) for h in result["history"]],
    }
    with open(os.path.join(out, "metrics.json"), "w") as f:
        json.dump(report, f, indent=1)
    return report


def run_demo(out: str, steps: int | None = None, minutes: float | None = None) -> dict:
    """Both parts, printing their tables and where the pictures are."""
    t0 = time.time()
    shipped = reconstruct_with_shipped(os.path.join(out, "shipped"))
    r = shipped["refine"]
    print(
        "\n1. Reconstruct: the shipped model (pretrained:small) on "
        f"{len(shipped['per_scene']) // 3} held-out procedural scenes, 8 inputs -> 2 targets:"
    )
    print(summary_table(shipped["summary"]))
    m, f = r["model"], r["refined"]
    print(
        f"the first {r['scenes']} scenes refined {r['steps']} steps against their inputs: held-out PSNR "
        f"{m['psnr']:.2f} -> {f['psnr']:.2f} dB, LPIPS {m['lpips']:.3f} -> {f['lpips']:.3f}, input views "
        f"{m['input_psnr']:.2f} -> {f['input_psnr']:.2f} dB"
    )
    scratch = train_from_scratch(os.path.join(out, "scratch"), steps=steps, minutes=minutes)
    print("\n2. Train from scratch: the tiny demo model, 4 inputs -> 2 targets:")
    for e in scratch["evals"]:
        print(f"   step {e['step']:5d}: held-out PSNR {e['psnr']:.2f} dB")
    print(summary_table(scratch["summary"]))
    curve = scratch["loss_curve"]
    first, last = np.mean([c[1] for c in curve[:3]]), np.mean([c[1] for c in curve[-3:]])
    total = time.time() - t0
    print(
        f"loss {first:.4f} -> {last:.4f}; trained {scratch['train_seconds'] / 60:.1f} min, total {total / 60:.1f} min"
    )
    print(
        f"pictures: {out}/shipped/grid_*.png (shipped model), {out}/scratch/grid_*.png (from scratch); "
        f"metrics: {out}/*/metrics.json"
    )
    return {"shipped": shipped, "scratch": scratch, "total_seconds": total}
