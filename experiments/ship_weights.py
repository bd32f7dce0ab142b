"""Ship a trained model inside the package: evaluate it, write its pictures, pack its weights.

Run:  python experiments/ship_weights.py --workdir ~/runs/small --config small --name small

Evaluates the newest checkpoint of ``--workdir`` on the experiment's held-out procedural
scenes (the model beside both baselines, with the diagnostics), writes the picture grids and
``metrics.json`` to ``experiments/results/<name>/`` together with the run's training log
(``train_log.json`` and the evaluation lines of ``train.log``), and packs the parameters as
``llrmpp_jax/weights/<name>.{npz,json,reference.npz}`` (:func:`llrmpp_jax.pretrained.export_pretrained`):
float16, SHA-256, model config, experiment file, source commit (``COMMIT`` in the workdir,
written when the run was started), step count and the held-out metrics. A run fine-tuned from
shipped weights (``llrmpp train --init pretrained:NAME``, recorded in its ``train_log.json``)
adds their steps to its own and records what it started from (their SHA-256, experiment and
commits), read before they are replaced.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess

import numpy as np

from llrmpp_jax.data.image_io import write_image
from llrmpp_jax.evaluate import evaluate, scene_picture, summary_table
from llrmpp_jax.experiment import load_experiment
from llrmpp_jax.experiment_data import eval_samples
from llrmpp_jax.metrics import load_lpips_params
from llrmpp_jax.params_io import load_params
from llrmpp_jax.pretrained import PREFIX, WEIGHTS_DIR, export_pretrained, read_meta

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


def main() -> None:
    p = argparse.ArgumentParser(description=(__doc__ or "").splitlines()[0])
    p.add_argument("--workdir", required=True, help="the training workdir (its newest checkpoint is shipped)")
    p.add_argument("--config", required=True, help="the experiment file it was trained with")
    p.add_argument(
        "--name", required=True, help="shipped name: llrmpp_jax/weights/<name>.*, --checkpoint pretrained:<name>"
    )
    p.add_argument("--pictures", type=int, default=6, help="picture grids to write (first held-out scenes)")
    args = p.parse_args()

    exp = load_experiment(args.config)
    params, cfg = load_params(args.workdir, exp.model)
    stage = exp.stages[-1]
    samples, names = eval_samples(exp, stage)
    rows, summary, _ = evaluate(params, cfg, samples, load_lpips_params(), names)
    out = os.path.join(ROOT, "experiments", "results", args.name)
    os.makedirs(out, exist_ok=True)
    for i in range(min(args.pictures, len(samples))):
        write_image(os.path.join(out, f"grid_{i}.png"), scene_picture(params, cfg, samples[i]))

    log_path = os.path.join(args.workdir, "train_log.json")
    init = None
    if os.path.isfile(log_path):
        shutil.copy(log_path, os.path.join(out, "train_log.json"))
        with open(log_path) as f:
            init = json.load(f).get("init")
    # Training steps behind the shipped params: the newest checkpoint of every stage (load_params
    # took the last stage's), summed over the curriculum, plus those of shipped start weights.
    steps = sum(
        max(int(d) for d in os.listdir(os.path.join(args.workdir, "checkpoints", s.name)) if d.isdigit())
        for s in exp.stages
    )
    started_from = None
    if init is not None and init.startswith(PREFIX):
        before = read_meta(init[len(PREFIX) :])
        steps += before["steps"]
        started_from = {
            "init": init,
            "sha256": before["sha256"],
            "steps": before["steps"],
            "experiment": before["experiment"],
            "trained_at_commit": before["trained_at_commit"],
        }
    elif init is not None:
        started_from = {"init": init}
    if os.path.isfile(os.path.join(args.workdir, "train.log")):
        with open(os.path.join(args.workdir, "train.log"), errors="replace") as f:
            lines = [ln.strip() for ln in f.read().replace("\r", "\n").splitlines() if "held-out PSNR" in ln]
        with open(os.path.join(out, "eval_log.txt"), "w") as f:
            f.write("\n".join(lines) + "\n")
    commit_file = os.path.join(args.workdir, "COMMIT")
    commit = open(commit_file).read().strip() if os.path.isfile(commit_file) else "unknown"
    head = subprocess.run(
        ["git", "rev-parse", "--short", "HEAD"], cwd=ROOT, capture_output=True, text=True
    ).stdout.strip()

    first = samples[0]
    num_frames = exp.data.procedural.num_frames
    reference = {
        "seed": int(exp.data.eval_seed_offset),
        "height": int(first["target_images"].shape[1]),
        "width": int(first["target_images"].shape[2]),
        "num_frames": num_frames,
        "inputs": [int(i) for i in np.linspace(0, num_frames - 2, stage.num_inputs).round()],
        "target": num_frames - 1,
    }
    record = {
        "experiment": os.path.relpath(os.path.abspath(args.config), ROOT),
        "trained_at_commit": commit,
        "shipped_at_commit": head,
        "steps": steps,
        "held_out": summary,
        "held_out_scenes": len(samples),
        "results": os.path.relpath(out, ROOT),
    }
    if started_from is not None:
        record["started_from"] = started_from
    meta = export_pretrained(params, cfg, args.name, record, reference)
    with open(os.path.join(out, "metrics.json"), "w") as f:
        json.dump({"summary": summary, "per_scene": rows, "steps": steps, "commit": commit}, f, indent=1)
    print(summary_table(summary))
    size = os.path.getsize(os.path.join(WEIGHTS_DIR, f"{args.name}.npz"))
    print(
        f"shipped {args.name}: {meta['num_params']:,} params, {size / 1e6:.2f} MB, sha256 {meta['sha256'][:16]}...; "
        f"pictures and metrics in {os.path.relpath(out, ROOT)}"
    )


if __name__ == "__main__":
    main()
