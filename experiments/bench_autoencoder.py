"""Can the model re-render the view it was given? One input view, the target is that view.

Run (PYTHONPATH=. python experiments/bench_autoencoder.py ...):
      --steps 1000
      --steps 1000 --init-std lecun
      --steps 600 --mode color
      --steps 4000 --init-std lecun --k 16 --feature-dim 32
      --steps 2000 --init-std lecun --anchors grid --scale-bias -3.0
      --steps 2000 --init-std lecun --k 16 --feature-dim 32 --canvas ideal

With one input view every Gaussian projects back onto the pixels it came from, whatever its
depth, so geometry plays no part: the score measures only the path that carries a patch's
detail, image -> token -> Gaussian features -> splatted canvas -> decoder -> pixels (colour
mode: image -> token -> per-pixel SH colour). Fresh procedural scenes every step (batch 2,
64x64), the demo experiment's model (its Gaussian head started as ``--anchors`` and
``--scale-bias`` say) with ``--pattern`` (default ``{4T}x1``, twice as fast as
``{1T3M}`` on a CPU), MSE, AdamW with warmup and cosine (the trainer's optimizer). Prints the
mean training PSNR of the last 100 steps every 200 steps and writes
``experiments/results/learning/autoencoder_<name>.json``. For scale (64x64 procedural frames):
the 8x8 block mean of an image scores 21.6 dB, the 4x4 block mean 23.2 dB, and a rank-16 /
rank-64 linear code (PCA) of its 8x8 patches 25.9 / 33.9 dB.
"""

from __future__ import annotations

import argparse
import json
import os
import time
from dataclasses import replace

import jax
import numpy as np

from llrmpp_jax import config as C
from llrmpp_jax import train as T
from llrmpp_jax.data import ProceduralConfig
from llrmpp_jax.data.preprocess import ViewGeometry, make_sample
from llrmpp_jax.data.synthetic import procedural_scene
from llrmpp_jax.experiment import StageConfig, load_experiment
from llrmpp_jax.gaussians import Gaussians
from llrmpp_jax.losses import rgb_loss
from llrmpp_jax.model import LongLRMPP, append_target_rays, init_params, partition_logits, reconstruct
from llrmpp_jax.nn.initializers import parse_init_std
from llrmpp_jax.objective import make_objective
from llrmpp_jax.trainer import optimizer_config

RESULTS = os.path.join(os.path.dirname(os.path.abspath(__file__)), "results", "learning")
SIZE, FRAMES, BATCH = 64, 16, 2


def model_config(args: argparse.Namespace) -> C.ModelConfig:
    """The demo experiment's model with the command line's changes."""
    m = load_experiment("demo").model
    head = replace(
        m.head,
        mode=args.mode,
        sh_degree=0,
        init_std=args.init_std,
        scale_bias=args.scale_bias,
        anchors=args.anchors,
        gaussians_per_token=m.head.gaussians_per_token if args.k is None else args.k,
        feature_dim=m.head.feature_dim if args.feature_dim is None else args.feature_dim,
    )
    return replace(
        m,
        backbone=replace(m.backbone, pattern=args.pattern),
        head=head,
        decoder=replace(m.decoder, init_std=args.init_std),
    )


def ideal_canvas_render(
    params: dict, cfg: C.ModelConfig, g: Gaussians, c2w: jax.Array, intrinsics: jax.Array
) -> jax.Array:
    """RGB ``[B, 1, H, W, 3]`` of the one input view with the splat replaced by an ideal canvas:
    Gaussian k of each token paints only canvas pixel ``(k // m, k % m)`` of its token's
    ``m x m`` canvas patch (m = q / r, K = m*m), with ``opacity * partition weight * feature``
    (what compositing gives where one Gaussian covers a pixel alone), then the model's decoder.
    Where the Gaussians are, how big and how they overlap play no part."""
    m = cfg.decoder.token_stride // cfg.decoder.canvas_ratio
    b, n, f = g.features.shape
    s = cfg.decoder.partitions
    h = w = SIZE // cfg.decoder.token_stride
    weights = jax.nn.softmax(partition_logits(params, cfg, g), axis=-1)  # [B, N, S]
    paint = g.opacities[..., None, None] * weights[..., None] * g.features[:, :, None, :]  # [B, N, S, F]
    canvas = paint.reshape(b, 1, h, w, m, m, s, f).transpose(0, 1, 6, 2, 4, 3, 5, 7).reshape(b, 1, s, h * m, w * m, f)
    canvas = append_target_rays(canvas, c2w, intrinsics, cfg.decoder.canvas_ratio)[:, 0]  # one target: the input view
    out = LongLRMPP(cfg).apply({"params": params}, canvas, method=lambda mod, c: mod.decoder(c, ("rgb",)))
    return out["rgb"][:, None]  # pyright: ignore[reportArgumentType, reportCallIssue] -- flax's apply is typed loosely; this module returns a dict of arrays


def main() -> None:
    p = argparse.ArgumentParser(description=(__doc__ or "").splitlines()[0])
    p.add_argument("--name", default=None, help="result name (default: from the options)")
    p.add_argument("--steps", type=int, default=1000, help="training steps")
    p.add_argument("--lr", type=float, default=2e-3, help="peak learning rate")
    p.add_argument("--mode", default="feature", choices=("feature", "color"), help="Gaussian head mode")
    p.add_argument("--pattern", default="{4T}x1", help="backbone block pattern")
    p.add_argument(
        "--init-std", type=parse_init_std, default=0.02, help="std of the head and decoder linears, or 'lecun'"
    )
    p.add_argument("--k", type=int, default=None, help="Gaussians per token (default: the demo model's)")
    p.add_argument("--feature-dim", type=int, default=None, help="feature width F (default: the demo model's)")
    # The head's start defaults to the demo's before it moved to the grid, so the runs of the
    # earlier rounds (docs/lab-notes.md, "Learning at small scale") reproduce with their own
    # command lines.
    p.add_argument(
        "--scale-bias",
        type=float,
        default=-2.5,
        help="log-scale bias of the Gaussians (default -2.5; the demo now -3.0; Long-LRM -6.9)",
    )
    p.add_argument(
        "--anchors",
        default="centre",
        choices=("centre", "grid"),
        help="where a token's Gaussians start: all at the patch centre (default), or on a sub-grid",
    )
    p.add_argument(
        "--canvas",
        default="splat",
        choices=("splat", "ideal"),
        help="the decoder's canvas: the splat (default), or an ideal one, each Gaussian on its own "
        "canvas pixel (feature mode, K = (q/r)^2; see ideal_canvas_render)",
    )
    p.add_argument("--seed", type=int, default=0, help="data and init seed")
    args = p.parse_args()
    name = args.name or (
        f"{args.mode}_{args.init_std or 'lecun'}_{args.pattern.strip('{}x1')}"
        + (f"_k{args.k}" if args.k is not None else "")
        + (f"_f{args.feature_dim}" if args.feature_dim is not None else "")
        + (f"_s{args.scale_bias:g}" if args.scale_bias != -2.5 else "")
        + ("_grid" if args.anchors == "grid" else "")
        + ("_ideal_canvas" if args.canvas == "ideal" else "")
    )
    cfg = model_config(args)
    cells = (cfg.decoder.token_stride // cfg.decoder.canvas_ratio) ** 2
    if args.canvas == "ideal" and (
        args.mode != "feature" or cfg.head.gaussians_per_token != cells or cfg.token_stride != cfg.decoder.token_stride
    ):
        p.error(f"--canvas ideal needs feature mode with --k {cells} (one Gaussian per canvas pixel of a token)")
    pc = ProceduralConfig(height=SIZE, width=SIZE, num_frames=FRAMES)
    geom = ViewGeometry(resize_h=SIZE, multiple=cfg.size_multiple, square_crop=True)
    stage = StageConfig(
        name="ae",
        steps=args.steps,
        global_batch=BATCH,
        num_inputs=1,
        num_targets=1,
        resize_h=SIZE,
        lr=args.lr,
        warmup_steps=50,
    )
    opt_cfg = optimizer_config(stage)
    optimizer, schedule = T.make_optimizer(opt_cfg), T.make_schedule(opt_cfg)

    objective = make_objective(cfg)  # MSE

    def loss_fn(params, batch, key):
        if args.canvas == "splat":  # the training objective with the input view as the target
            return objective(
                params, {**batch, **{f"target_{k}": batch[f"input_{k}"] for k in ("images", "c2w", "intrinsics")}}, key
            )
        g = reconstruct(params, cfg, batch["input_images"], batch["input_c2w"], batch["input_intrinsics"])
        rgb = ideal_canvas_render(params, cfg, g, batch["input_c2w"], batch["input_intrinsics"])
        return rgb_loss(
            rgb.reshape(-1, SIZE, SIZE, 3),
            batch["input_images"].reshape(-1, SIZE, SIZE, 3),
            None,
            perceptual_weight=0.0,
        )

    mesh = T.make_data_mesh()
    params = init_params(jax.random.key(args.seed + 1), cfg, 1, SIZE, SIZE)
    state = T.replicate_on_mesh(T.init_train_state(params, optimizer, jax.random.key(args.seed)), mesh)
    run = T.sharded_train_step(T.make_train_step(loss_fn, optimizer, schedule), mesh, donate=True)
    rng = np.random.default_rng(args.seed)
    psnrs, log, t0 = [], [], time.time()
    for step in range(1, args.steps + 1):
        samples = []
        for _ in range(BATCH):
            scene = procedural_scene(int(rng.integers(1 << 30)), pc)
            s = make_sample(scene, rng.integers(FRAMES, size=1), np.arange(1), geom)
            s.pop("scene_scale")
            samples.append(s)
        batch = {k: np.stack([s[k] for s in samples]) for k in samples[0]}
        state, metrics = run(state, T.shard_for_mesh(batch, mesh))
        psnrs.append(float(metrics["psnr"]))
        if step % 200 == 0 or step == args.steps:
            log.append({"step": step, "psnr_last_100": float(np.mean(psnrs[-100:])), "wall_s": time.time() - t0})
            print(
                f"step {step:5d}  mean PSNR of the last 100 steps {log[-1]['psnr_last_100']:.2f} dB  "
                f"{log[-1]['wall_s']:.0f} s",
                flush=True,
            )
    os.makedirs(RESULTS, exist_ok=True)
    with open(os.path.join(RESULTS, f"autoencoder_{name}.json"), "w") as f:
        json.dump({"name": name, "args": vars(args), "log": log}, f, indent=1)


if __name__ == "__main__":
    main()
