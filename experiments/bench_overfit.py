"""Overfit one procedural scene: can a small model re-render its inputs and the views between them?

Run:  python experiments/bench_overfit.py --name feat_base --steps 1500
      python experiments/bench_overfit.py --name colour --mode color --steps 600
      python experiments/bench_overfit.py --name depth_aux --decoder-depth-weight 1 --steps 300
      python experiments/bench_overfit.py --name from_small --init pretrained:small --random-inputs

One seeded scene of ``--frames`` frames; ``--inputs`` evenly spaced frames are the fixed
inputs, the frames half-way between consecutive inputs are held out (never a target), and
every other frame (inputs included) is a training target (``--random-inputs``: each step
also draws its inputs from those frames; evaluation keeps the fixed inputs). The scene is ray-cast once and
kept in memory, so a step costs only the model. ``--dense D`` adds ``D - 1`` views between
consecutive frames (a spline through the path) as training targets, except within ``--hole``
frames of a held-out frame: the decoder then sees a continuum of target cameras and cannot
memorise a few. Each step renders ``--targets`` training
frames drawn at random; MSE, plus with ``--decoder-depth-weight`` the paper's depth loss
on the decoder's depth head (log smooth-L1 + ``--depth-aux-weight`` x (gradient + normal));
AdamW with warmup + cosine (the trainer's optimizer). ``--init`` starts from trained weights
(a workdir, a params folder or ``pretrained:NAME``) and their model config: per-scene
fine-tuning of a model that has already learned across scenes.

Writes ``experiments/results/learning/<name>.json`` (config, steps, wall time, PSNR on the
input views and on the held-out views, the held-out views' PSNR of the two baselines of
``evaluate``: mean input colour and nearest input view, Gaussian statistics; with depth, depth metrics of
the model and of the best constant) and ``<name>.png``: the first row the inputs, then per
shown view: target, prediction, |error| x4, nearest input; with depth also
``<name>_depth.png`` (target and predicted depth of the shown views on one colour scale).
"""

from __future__ import annotations

import argparse
import glob
import json
import os
import time
from dataclasses import replace

import jax
import jax.numpy as jnp
import numpy as np

from llrmpp_jax import config as C
from llrmpp_jax import model as model_module
from llrmpp_jax import train as T
from llrmpp_jax.capture.render import spline_path
from llrmpp_jax.data import ProceduralConfig
from llrmpp_jax.data.image_io import write_image
from llrmpp_jax.data.preprocess import ViewGeometry, make_sample
from llrmpp_jax.data.scene import Scene
from llrmpp_jax.data.synthetic import procedural_layout, procedural_scene
from llrmpp_jax.evaluate import baseline_predictions, gaussian_statistics, picture_grid
from llrmpp_jax.experiment import StageConfig
from llrmpp_jax.metrics import depth_metrics, psnr
from llrmpp_jax.model import init_params, reconstruct, render
from llrmpp_jax.nn.initializers import parse_init_std
from llrmpp_jax.objective import LossWeights, make_objective
from llrmpp_jax.params_io import load_params
from llrmpp_jax.refine import heldout_psnr, refine
from llrmpp_jax.trainer import optimizer_config

RESULTS = os.path.join(os.path.dirname(os.path.abspath(__file__)), "results", "learning")


def model_config(args: argparse.Namespace) -> C.ModelConfig:
    """The demo's tiny model with the command line's changes."""
    base = C.tiny()
    head = C.GaussianHeadConfig(
        mode=args.mode,
        gaussians_per_token=args.k,
        feature_dim=args.f,
        sh_degree=0,
        max_dist=args.max_dist,
        scale_bias=args.scale_bias,
        scale_max=args.scale_max,
        opacity_bias=args.opacity_bias,
        init_std=args.init_std,
        anchors=args.anchors,
    )
    decoder = replace(
        base.decoder,
        canvas_ratio=args.ratio,
        token_stride=args.stride,
        dim=args.dec_dim,
        init_std=head.init_std,
        depth_bias=args.depth_bias,
    )
    backbone = replace(base.backbone, dims=(args.dim,), pattern=args.pattern, num_layers=args.layers)
    outputs = ("rgb", "depth") if args.decoder_depth_weight else ("rgb",)
    return replace(base, head=head, decoder=decoder, backbone=backbone, patch_size=args.patch, outputs=outputs)


def split_frames(
    num_frames: int, num_inputs: int, dense: int = 1, hole: float = 1.0
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``(inputs, held_out, train_targets)`` indices into the path of ``(num_frames - 1) * dense
    + 1`` views (:func:`path_scene`; view ``i * dense`` is frame ``i``): inputs evenly spaced
    frames, held-out frames half-way between consecutive inputs, training targets every view at
    least ``hole`` frames from a held-out frame, inputs included (``dense=1, hole=1``: every
    frame but the held-out ones)."""
    gap = num_frames // num_inputs
    inputs = np.arange(num_inputs) * gap + gap // 2
    held = (inputs[:-1] + inputs[1:]) // 2
    t = np.arange((num_frames - 1) * dense + 1) / dense
    far = np.abs(t[:, None] - held[None, :]).min(axis=1) >= hole - 1e-9
    return inputs * dense, held * dense, np.flatnonzero(far)


def path_scene(seed: int, cfg: ProceduralConfig, dense: int) -> Scene:
    """The procedural scene of ``seed`` seen from its camera path with ``dense - 1`` more views
    between consecutive frames, on :func:`~llrmpp_jax.capture.render.spline_path` through the
    frames (view ``i * dense`` is frame ``i`` exactly). ``dense=1``: the scene as drawn."""
    if dense == 1:
        return procedural_scene(seed, cfg)
    _, c2w, intrinsics, _ = procedural_layout(seed, cfg)
    if not np.allclose(intrinsics, intrinsics[:1]):
        raise ValueError(f"--dense: scene {seed} has per-frame intrinsics; the dense path needs one camera")
    n = (cfg.num_frames - 1) * dense + 1
    path = spline_path(c2w, n)
    path[::dense] = c2w
    return procedural_scene(seed, cfg, cameras=(path, np.repeat(intrinsics[:1], n, axis=0)))


def depth_scores(pred: np.ndarray, target: np.ndarray) -> dict[str, dict[str, float]]:
    """Mean :func:`~llrmpp_jax.metrics.depth_metrics` of ``pred`` [V, H, W] against
    ``target`` and of the best constant: the one depth (geometric mean of the valid target
    pixels) that minimises the log depth loss over these views, the simplest baseline."""
    valid = np.isfinite(target) & (target > 0)
    constant = np.full_like(target, np.exp(np.mean(np.log(target[valid]))))
    return {
        name: {k: float(np.nanmean(v)) for k, v in depth_metrics(jnp.asarray(p), jnp.asarray(target)).items()}
        for name, p in (("model", pred), ("constant", constant))
    }


def write_depth_figure(path: str, target: np.ndarray, pred: np.ndarray) -> None:
    """Target (top) and predicted (bottom) depth [V, H, W] of V views, one colour scale per view."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(2, len(target), figsize=(3 * len(target), 6), squeeze=False)
    for v in range(len(target)):
        lo, hi = np.percentile(target[v][target[v] > 0], [2, 98])
        for row, (name, d) in enumerate((("target", target[v]), ("predicted", pred[v]))):
            im = axes[row, v].imshow(d, vmin=lo, vmax=hi, cmap="viridis")
            axes[row, v].set_title(f"{name} depth, view {v}")
            axes[row, v].axis("off")
        fig.colorbar(im, ax=axes[:, v], shrink=0.6, label="scene units")
    fig.savefig(path, dpi=80)
    plt.close(fig)


def table() -> str:
    """Markdown table of every run in ``RESULTS``, in name order; ``change`` lists the
    arguments that differ from the defaults."""
    lines = [
        "| run | change | steps | wall (min) | s/step | input PSNR | held-out PSNR | held-out nearest view / mean "
        "colour | held-out delta<1.25 (constant) | mean scale | mean opacity |",
        "|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    skip, defaults = {"name", "steps", "minutes", "table"}, vars(parser().parse_args([]))
    for path in sorted(glob.glob(os.path.join(RESULTS, "*.json"))):
        with open(path) as f:
            r = json.load(f)
        if "held_out_psnr" not in r:  # another benchmark's record (autoencoder_*, pilots_*)
            continue
        change = ", ".join(f"{k}={v}" for k, v in r["args"].items() if k not in skip and v != defaults.get(k))
        g, d = r["gaussians"], r.get("depth", {}).get("held_out")
        delta = f"{d['model']['delta_1_25']:.3f} ({d['constant']['delta_1_25']:.3f})" if d else "-"
        b = r.get("held_out_baselines_psnr")
        base = f"{b['nearest_view']:.2f} / {b['mean_colour']:.2f}" if b else "-"
        lines.append(
            f"| {r['name']} | {change or 'defaults'} | {r['steps']} | {r['wall_min']:.1f} | {r['step_s']:.2f} "
            f"| {r['input_psnr']:.2f} | {r['held_out_psnr']:.2f} | {base} | {delta} | {g['mean_scale']:.3f} "
            f"| {g['mean_opacity']:.2f} |"
        )
    return "\n".join(lines)


def parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(description=(__doc__ or "").splitlines()[0])
    p.add_argument("--name", help="run name: results/learning/<name>.json and .png")
    p.add_argument("--table", action="store_true", help="print the Markdown table of every stored run and exit")
    p.add_argument("--seed", type=int, default=3, help="procedural scene seed")
    p.add_argument("--res", type=int, default=64, help="square image side (pixels)")
    p.add_argument(
        "--scene-scale",
        type=float,
        default=1.0,
        help="make_sample's scene_scale: input cameras in [-1/s, 1/s]^3, depths x 1/s "
        "(0.1: depths ~15 units, as in the notebooks' 8-frame windows)",
    )
    p.add_argument("--frames", type=int, default=16, help="frames of the scene's camera path")
    p.add_argument("--inputs", type=int, default=4, help="fixed input views")
    p.add_argument(
        "--dense",
        type=int,
        default=1,
        help="views per frame step of the camera path: dense-1 extra training views between "
        "consecutive frames (1: the frames only)",
    )
    p.add_argument(
        "--hole",
        type=float,
        default=1.0,
        help="training targets keep at least this many frames from every held-out frame",
    )
    p.add_argument("--targets", type=int, default=2, help="training target views per step")
    p.add_argument("--steps", type=int, default=1000, help="training steps (0: score the --init weights as they are)")
    p.add_argument("--lr", type=float, default=2e-3, help="peak learning rate")
    p.add_argument("--warmup", type=int, default=50, help="linear warmup steps")
    p.add_argument("--mode", default="feature", choices=("feature", "color"), help="Gaussian head mode")
    p.add_argument("--k", type=int, default=4, help="Gaussians per token (feature mode)")
    p.add_argument("--f", type=int, default=16, help="feature dimension (feature mode)")
    p.add_argument("--dim", type=int, default=64, help="backbone width")
    p.add_argument("--pattern", default="{1T3M}x1", help="backbone block pattern (T transformer, M Mamba2)")
    p.add_argument("--layers", type=int, default=4, help="backbone blocks (the pattern is tiled to this many)")
    p.add_argument("--patch", type=int, default=8, help="backbone patch size")
    p.add_argument("--ratio", type=int, default=2, help="decoder canvas ratio r")
    p.add_argument("--stride", type=int, default=8, help="decoder token stride q")
    p.add_argument("--dec-dim", type=int, default=64, help="decoder width E")
    p.add_argument("--max-dist", type=float, default=8.0, help="distance = sigmoid(raw) * max_dist")
    p.add_argument("--scale-bias", type=float, default=-2.5, help="log-scale bias")
    p.add_argument(
        "--anchors",
        default="centre",
        choices=("centre", "grid"),
        help="where a token's Gaussians start (GaussianHeadConfig.anchors)",
    )
    p.add_argument("--scale-max", type=float, default=-1.2, help="log-scale clamp")
    p.add_argument("--opacity-bias", type=float, default=-2.0, help="opacity logit bias")
    p.add_argument(
        "--init-std", type=parse_init_std, default=0.02, help="std of the head and decoder linears, or 'lecun'"
    )
    p.add_argument(
        "--random-inputs",
        action="store_true",
        help="draw the inputs from the training frames each step (evaluation keeps the fixed ones)",
    )
    p.add_argument(
        "--no-target-rays",
        action="store_true",
        help="a diagnostic: zeros in place of the target's Plucker rays at the decoder's input "
        "(the paper has them), so target views differ only by their splatted canvases",
    )
    p.add_argument(
        "--refine-steps",
        type=int,
        default=0,
        help="a diagnostic: after training, fit the fixed inputs' Gaussians directly to every "
        "training view for this many steps (llrmpp_jax.refine, decoder frozen) and score "
        "the held-out views again; 0: none",
    )
    p.add_argument(
        "--depth-weight",
        type=float,
        default=0.0,
        help="weight of a depth loss on the Gaussians' own splatted depth (expected z at "
        "canvas resolution) against the procedural ground truth; 0: none",
    )
    p.add_argument(
        "--decoder-depth-weight",
        type=float,
        default=0.0,
        help="weight of the paper's depth loss on the decoder's depth head (adds the 'depth' output); 0: RGB only",
    )
    p.add_argument(
        "--depth-bias",
        type=float,
        default=0.0,
        help="DecoderConfig.depth_bias: log-depth offset of the depth head (depth = exp(head + bias))",
    )
    p.add_argument(
        "--depth-aux-weight",
        type=float,
        default=0.1,
        help="lambda_grad = lambda_normal of that depth loss (the paper's 0.1)",
    )
    p.add_argument("--minutes", type=float, default=8.0, help="wall-clock budget of the training loop")
    p.add_argument(
        "--init",
        default=None,
        help="start from these weights (workdir, params folder or pretrained:NAME) and their model "
        "config; the model flags above are then ignored",
    )
    return p


def main() -> None:
    p = parser()
    args = p.parse_args()
    if args.table:
        print(table())
        return
    if not args.name:
        p.error("--name is required to train")

    if args.no_target_rays:  # model.render looks the function up at call time
        model_module.append_target_rays = lambda canvas, c2w, intrinsics, ratio: jnp.concatenate(
            [canvas, jnp.zeros((*canvas.shape[:-1], 6), canvas.dtype)], axis=-1
        )
    init = load_params(args.init) if args.init else None
    cfg = model_config(args) if init is None else init[1]
    if init is not None and args.decoder_depth_weight and "depth" not in cfg.outputs:
        p.error(f"--decoder-depth-weight: the model of --init {args.init} has no depth head")
    scene = path_scene(args.seed, ProceduralConfig(height=args.res, width=args.res, num_frames=args.frames), args.dense)
    inputs, held, train = split_frames(args.frames, args.inputs, args.dense, args.hole)
    geom = ViewGeometry(resize_h=args.res, multiple=cfg.size_multiple, square_crop=True)
    t0 = time.time()
    everything = make_sample(
        scene, inputs, np.arange(len(scene.c2w)), geom, with_depth=True, scene_scale=args.scene_scale
    )  # targets = every frame
    data_s = time.time() - t0
    frames = {k[len("target_") :]: v for k, v in everything.items() if k.startswith("target_")}
    fixed = {k: v[None] for k, v in everything.items() if k.startswith("input_")}

    stage = StageConfig(
        name="overfit",
        steps=max(args.steps, 1),
        global_batch=1,
        num_inputs=args.inputs,
        num_targets=args.targets,
        resize_h=args.res,
        lr=args.lr,
        warmup_steps=args.warmup,
    )
    opt_cfg = optimizer_config(stage)
    optimizer, schedule = T.make_optimizer(opt_cfg), T.make_schedule(opt_cfg)

    # MSE, the decoder's depth loss and the Gaussians' own depth loss, as the command line weighs them
    loss_fn = make_objective(
        cfg,
        LossWeights(
            depth=args.decoder_depth_weight,
            depth_grad=args.depth_aux_weight,
            depth_normal=args.depth_aux_weight,
            gaussian_depth=args.depth_weight,
        ),
    )

    mesh = T.make_data_mesh()
    key = jax.random.key(0)
    params = init_params(jax.random.fold_in(key, 1), cfg, args.inputs, args.res, args.res) if init is None else init[0]
    state = T.replicate_on_mesh(T.init_train_state(params, optimizer, key), mesh)
    run = T.sharded_train_step(T.make_train_step(loss_fn, optimizer, schedule), mesh, donate=True)
    rng = np.random.default_rng(args.seed)
    log, t_start, step = [], time.time(), 0
    while step < args.steps and (time.time() - t_start) / 60 < args.minutes:
        pick = rng.choice(train, args.targets, replace=False)
        if args.random_inputs:  # a fresh input subset: the decoder cannot memorise views
            ins = np.sort(rng.choice(train, args.inputs, replace=False))
            batch = {
                k: v[None]
                for k, v in make_sample(scene, ins, pick, geom, with_depth=True, scene_scale=args.scene_scale).items()
            }
            batch.pop("scene_scale")
        else:
            batch = dict(fixed, **{f"target_{k}": v[pick][None] for k, v in frames.items()})
        batch.pop("scene_scale", None)
        state, metrics = run(state, T.shard_for_mesh(batch, mesh))
        step += 1
        if step == 1:
            t_first = time.time()  # compile time excluded from the step time
        if step % 50 == 0 or step == 1:
            log.append({"step": step, "psnr": float(metrics["psnr"]), "wall_s": time.time() - t_start})
            print(f"step {step:5d}  train psnr {log[-1]['psnr']:.2f}  {log[-1]['wall_s']:.0f} s", flush=True)
    wall = time.time() - t_start
    step_s = (time.time() - t_first) / (step - 1) if step > 1 else float("nan")  # --steps 0: score --init as is
    params = jax.device_get(state.params)

    @jax.jit
    def view(params, c2w, intrinsics):
        g = reconstruct(params, cfg, fixed["input_images"], fixed["input_c2w"], fixed["input_intrinsics"])
        out = render(params, cfg, g, c2w[None], intrinsics[None], args.res, args.res, cfg.outputs)
        return {k: v[0] for k, v in out.images.items()}, g

    def score(views: np.ndarray) -> tuple[dict[str, np.ndarray], list[float]]:
        images, _ = view(params, frames["c2w"][views], frames["intrinsics"][views])
        rgb = images["rgb"]
        return (
            {k: np.asarray(v) for k, v in images.items()},
            [float(x) for x in psnr(jnp.clip(rgb, 0, 1), jnp.asarray(frames["images"][views]))],
        )

    pred_in, psnr_in = score(inputs)
    pred_held, psnr_held = score(held)
    held_sample = {
        "input_images": fixed["input_images"][0],
        "input_c2w": fixed["input_c2w"][0],
        "target_images": frames["images"][held],
        "target_c2w": frames["c2w"][held],
    }
    baselines = {
        name: float(np.mean(psnr(jnp.asarray(b), jnp.asarray(frames["images"][held]))))
        for name, b in baseline_predictions(held_sample).items()
    }
    _, g = view(params, frames["c2w"][held], frames["intrinsics"][held])
    result = {
        "name": args.name,
        "args": vars(args),
        "steps": step,
        "wall_min": wall / 60,
        "scene_s": data_s,
        "step_s": step_s,
        "input_psnr": float(np.mean(psnr_in)),
        "held_out_psnr": float(np.mean(psnr_held)),
        "input_psnr_per_view": psnr_in,
        "held_out_psnr_per_view": psnr_held,
        "held_out_baselines_psnr": baselines,
        "gaussians": {k: float(v) for k, v in gaussian_statistics(g).items()},
        "frames": {
            "inputs": (inputs // args.dense).tolist(),
            "held_out": (held // args.dense).tolist(),
            "training_views": len(train),
        },
        "log": log,
    }
    if args.refine_steps:  # one set of Gaussians for every training view: 3D-consistent by construction

        def views_of(v: np.ndarray) -> tuple[jax.Array, ...]:  # (images, c2w, intrinsics), [1, T, ...]
            return tuple(jnp.asarray(frames[k][v][None]) for k in ("images", "c2w", "intrinsics"))

        ref = views_of(train)
        fitted, info = refine(params, cfg, g, *ref, steps=args.refine_steps, progress=True)
        result["refine"] = {
            "steps": info.steps,
            "views": len(train),
            "loss_first_last": [float(info.losses[0]), float(info.losses[-1])],
            "splat_dropped": info.dropped,
            **{
                f"{name}_psnr": heldout_psnr(params, cfg, fitted, *views)
                for name, views in (("input", views_of(inputs)), ("held_out", views_of(held)), ("training", ref))
            },
        }
        print("refine:", json.dumps(result["refine"]))
    if args.decoder_depth_weight:
        result["depth"] = {
            "inputs": depth_scores(pred_in["depth"][..., 0], frames["depth"][inputs]),
            "held_out": depth_scores(pred_held["depth"][..., 0], frames["depth"][held]),
        }
        write_depth_figure(
            os.path.join(RESULTS, f"{args.name}_depth.png"), frames["depth"][held[:2]], pred_held["depth"][:2, ..., 0]
        )
    os.makedirs(RESULTS, exist_ok=True)
    with open(os.path.join(RESULTS, f"{args.name}.json"), "w") as f:
        json.dump(result, f, indent=1)
    shown = {
        "input_images": fixed["input_images"][0],
        "input_c2w": fixed["input_c2w"][0],
        "target_images": np.concatenate([frames["images"][held[:2]], frames["images"][inputs[:1]]]),
        "target_c2w": np.concatenate([frames["c2w"][held[:2]], frames["c2w"][inputs[:1]]]),
    }
    grid = picture_grid(shown, np.concatenate([pred_held["rgb"][:2], pred_in["rgb"][:1]]))
    write_image(os.path.join(RESULTS, f"{args.name}.png"), grid)
    print(
        json.dumps(
            {
                k: result[k]
                for k in (
                    "name",
                    "steps",
                    "wall_min",
                    "step_s",
                    "input_psnr",
                    "held_out_psnr",
                    "held_out_baselines_psnr",
                    "gaussians",
                )
            }
        )
    )


if __name__ == "__main__":
    main()
