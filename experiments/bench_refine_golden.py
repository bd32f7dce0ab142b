"""Post-prediction refinement on real captures from the golden (untrained) tiny Long-LRM.

Run:  PYTHONPATH=. python experiments/bench_refine_golden.py [--steps 50] [--size 64] [--inputs 8]

For fox (nerfstudio) and beer (COLMAP) in ../shared/data: the paper's evaluation split
(every 8th frame held out, k-means inputs among the rest), images resized to height
``--size`` keeping the aspect ratio, the converted golden ``state_dict.npz`` of
../shared/golden/long_lrm_tiny (random weights plus noise, colour mode), ``reconstruct``,
then ``refine`` for ``--steps`` steps on the input views (MSE, default learning rates).
Writes held-out-target PSNR before and after, the loss curve and timings (a 1-step run
first compiles; ``refine_s`` is the compiled run) to experiments/results/bench_refine_golden.json.
"""

from __future__ import annotations

import argparse
import json
import os
import time

import jax
import numpy as np

from llrmpp_jax import config as C
from llrmpp_jax.convert.long_lrm import convert_long_lrm
from llrmpp_jax.data.formats import read_colmap_scene, read_nerfstudio_scene
from llrmpp_jax.data.preprocess import ViewGeometry, make_sample
from llrmpp_jax.data.selection import eval_views
from llrmpp_jax.model import reconstruct
from llrmpp_jax.refine import heldout_psnr, refine

SHARED = os.path.join(os.path.dirname(__file__), "..", "..", "shared")
RESULTS = os.path.join(os.path.dirname(__file__), "results", "bench_refine_golden.json")


def golden_config() -> C.ModelConfig:
    """The tiny Long-LRM of ../shared/golden/long_lrm_tiny/config.json (colour mode)."""
    return C.ModelConfig(
        backbone=C.BackboneConfig(
            dims=(32, 64),
            pattern="mmt",
            num_layers=6,
            merge_layers=(3,),
            num_global_tokens=2,
            mamba=C.Mamba2Config(d_state=16, headdim=16, chunk_size=256),
            transformer=C.TransformerConfig(head_dim=16, qk_norm=False),
        ),
        head=C.GaussianHeadConfig(mode="color"),
    )


def scenes() -> dict:
    data = os.path.join(SHARED, "data")
    return {
        "fox": read_nerfstudio_scene(os.path.join(data, "fox")),
        "beer": read_colmap_scene(os.path.join(data, "beer", "sparse", "0"), os.path.join(data, "beer", "images")),
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=(__doc__ or "").splitlines()[0])
    ap.add_argument("--steps", type=int, default=50, help="refinement steps")
    ap.add_argument("--size", type=int, default=64, help="image height before rounding to the patch multiple")
    ap.add_argument("--inputs", type=int, default=8, help="input views (k-means)")
    a = ap.parse_args()
    cfg = golden_config()
    sd = dict(np.load(os.path.join(SHARED, "golden", "long_lrm_tiny", "state_dict.npz")))
    params = convert_long_lrm(sd, cfg)
    out = {"steps": a.steps, "size": a.size, "num_inputs": a.inputs, "device": str(jax.devices()[0]), "scenes": {}}
    for name, scene in scenes().items():
        inputs, targets = eval_views(scene.c2w, a.inputs)
        s = make_sample(scene, inputs, targets, ViewGeometry(resize_h=a.size, multiple=cfg.size_multiple))
        b = {k: v[None] for k, v in s.items()}
        g = jax.jit(reconstruct, static_argnums=1)(
            params, cfg, b["input_images"], b["input_c2w"], b["input_intrinsics"]
        )
        tgt = (b["target_images"], b["target_c2w"], b["target_intrinsics"])
        before = heldout_psnr(params, cfg, g, *tgt)  # pyright: ignore[reportArgumentType] -- a NumPy array where jax.Array is annotated: both work
        views = (b["input_images"], b["input_c2w"], b["input_intrinsics"])
        t0 = time.time()
        refine(params, cfg, g, *views, steps=1)  # compiles init, step and the final loss
        compile_s = time.time() - t0
        t0 = time.time()
        refined, info = refine(params, cfg, g, *views, steps=a.steps, progress=True)
        seconds = time.time() - t0
        after = heldout_psnr(params, cfg, refined, *tgt)  # pyright: ignore[reportArgumentType] -- a NumPy array where jax.Array is annotated: both work
        print(
            f"{name}: {g.means.shape[1]} Gaussians, {len(inputs)} inputs, {len(targets)} targets at "
            f"{s['input_images'].shape[1:3]}: PSNR before {before:.2f} / after {after:.2f} "
            f"(input loss {info.losses[0]:.4f} -> {info.losses[-1]:.4f}; compile + 1 step {compile_s:.1f} s, "
            f"{a.steps} steps {seconds:.1f} s)"
        )
        out["scenes"][name] = {
            "gaussians": int(g.means.shape[1]),
            "hw": list(s["input_images"].shape[1:3]),
            "inputs": inputs.tolist(),
            "targets": targets.tolist(),
            "psnr_before": before,
            "psnr_after": after,
            "input_loss": info.losses.tolist(),
            "dropped": info.dropped,
            "compile_and_one_step_s": compile_s,
            "refine_s": seconds,
        }
    with open(RESULTS, "w") as f:
        json.dump(out, f, indent=1)


if __name__ == "__main__":
    main()
