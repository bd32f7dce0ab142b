"""The paper's stage-4 training step *executed* on one accelerator: compile time, XLA's
memory analysis, the device's peak memory, the step time and its FLOPs, per attention
kernel; or (``--profile``) a per-op profile of one smaller step.

Run (one GPU or TPU):
    python -m llrmpp_jax.benchmarks.paper_step                                 # writes runs/bench/bench_paper_step.json
    python -m llrmpp_jax.benchmarks.paper_step --impls blockwise --steps 1     # the portable kernel only
    python -m llrmpp_jax.benchmarks.paper_step --profile --views 8,8 --out runs/profile_step.json   # stage 3's shapes
    python -m llrmpp_jax.benchmarks.paper_step --scale cpu                     # config.tiny(), 2 + 1 views: seconds

The repository's ``experiments/bench_train.py`` can only *compile* this step on a CPU (XLA's
memory analysis, no run). Here it runs: the ``dl3dv`` recipe's stage 4 (32 inputs + 8 targets at
544x960, one scene per device as in the paper's 64-GPU run, bf16 compute, remat everywhere as
``config.for_accelerators`` sets it, the sequential SSD inter-chunk recurrence, Long-LRM's
VGG19 perceptual term with random weights of its shapes unless the file names weights: the
cost does not depend on the weights), with the project's own step
(``objective.make_loss_fn`` -> ``train.make_train_step`` -> the runner's jit over a one-device
mesh, ``trainer.stage_runner``, donated state) and the model's parameters initialised as for training (on the host CPU:
``paper.host_init_params``, which spares the accelerator a slow XLA compile of the init of its own).
``--scale cpu`` swaps in ``config.tiny()`` (same stage, bf16, VGG19 term and code paths)
with 2 inputs + 1 target at 64x96 and the blockwise kernel.

The batch is synthetic (``paper.synthetic_batch``): uniform-noise images (content
changes nothing in a step whose shapes and capacities are static) seen from an orbit of
40 cameras around the origin, targets spread along it, so the Gaussians project into the
targets as in a real capture. Each kernel (``--impls``: ``cudnn`` on NVIDIA GPUs,
``blockwise`` anywhere, ``xla`` is only there to show it does not fit) is measured in its own
process, so its peak memory is its own. Reported per kernel: the first call's seconds
(compile + one step) and the compile's share, ``memory_analysis()`` (as ``bench_train.py``,
from a separate ahead-of-time compile, ``aot_compile_s``), the device's ``peak_bytes_in_use``, the median
of ``--steps`` synced step times after the first call, the last step's loss and splat
overflow (``splat_dropped``), and how many steps the trainer's guard skipped (``skipped_total``);
``xla_flops`` (XLA's cost analysis of that compiled step: a loop body counted once, cuDNN
calls not at all) and ``model_flops`` (``paper.train_step_model_flops``: the matrix
products of the loss's forward and backward, no recomputation), with ``tflops_per_s`` and
``peak_fraction`` of the card's dense bf16 peak from ``model_flops`` and the median step.
Set ``JAX_COMPILATION_CACHE_DIR`` (with ``JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS=0``) and
the AOT compile loads the step's executable from the cache instead of compiling it again.

``--profile``: ``llrmpp_jax.profiling.profile_program`` of one step (not donated: the same
state runs three times) at ``--views`` (default 8,8: stage 3's 8 inputs + 8 targets at
544x960), with the first kernel of ``--impls``; writes the per-phase and top-30 per-op
milliseconds as JSON and prints them as Markdown.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from dataclasses import replace

import jax
import jax.numpy as jnp
import numpy as np
import optax
from jax.sharding import Mesh

from llrmpp_jax import config as C
from llrmpp_jax import train as T
from llrmpp_jax.benchmarks.measure import environment, memory_analysis_bytes, throughput, xla_cost
from llrmpp_jax.benchmarks.paper import (
    PAPER_A100,
    check_case,
    host_init_params,
    profile_markdown,
    synthetic_batch,
    train_step_model_flops,
)
from llrmpp_jax.convert.vgg import vgg_layers
from llrmpp_jax.experiment import ExperimentConfig, StageConfig, load_experiment
from llrmpp_jax.nn.attention import ATTENTION_IMPLEMENTATIONS
from llrmpp_jax.nn.backbone import count_params
from llrmpp_jax.objective import load_perceptual
from llrmpp_jax.trainer import optimizer_config, stage_runner

GIB = 2.0**30
PAPER_STAGE4_DEVICES = 64  # paper Table 8: stage 4 trains a global batch of 64 on 64 GPUs


def make_step(
    exp: ExperimentConfig, stage: StageConfig, vgg_params: dict | None, mesh: Mesh | None = None, donate: bool = True
) -> tuple[T.Runner, optax.GradientTransformation]:
    """The trainer's runner for ``stage`` (``trainer.stage_runner``: settings as
    ``trainer.train``; ``donate``d state) over ``mesh`` (default: a mesh of the first device)
    and its optimizer."""
    opt_cfg = optimizer_config(stage)
    optimizer = T.make_optimizer(opt_cfg)
    mesh = T.make_data_mesh(jax.devices()[:1]) if mesh is None else mesh
    return stage_runner(exp, stage, vgg_params, optimizer, T.make_schedule(opt_cfg), mesh, donate=donate), optimizer


def paper_stage4_experiment() -> tuple[ExperimentConfig, StageConfig]:
    """The ``dl3dv`` recipe and its stage 4 (32 inputs + 8 targets at 960x540)."""
    exp = load_experiment("dl3dv")
    return exp, exp.stages[3]


def perceptual_for_compile(exp: ExperimentConfig) -> dict | None:
    """The perceptual net's params for a benchmark step: the real ones where the experiment
    names them, else (VGG19 without ``vgg19_path``) He-normal random weights (seed 0) of
    VGG19's conv1_1..conv5_2 shapes: a step's memory and time depend on shapes only.

    Not zeros: with all-zero VGG weights the stage-4 step's perceptual term came back NaN
    on some runs and finite on others (jax 0.10.2, CPU; 2 inputs of 32x64), so every step
    was skipped as non-finite; random weights gave finite losses every time.
    """
    if exp.perceptual_net != "vgg19" or exp.vgg19_path or not exp.perceptual_weight:
        return load_perceptual(exp)
    rng = np.random.default_rng(0)
    return {
        name: {
            "kernel": jnp.asarray(rng.normal(0.0, np.sqrt(2.0 / (9 * cin)), (3, 3, cin, cout)), jnp.float32),
            "bias": jnp.zeros((cout,), jnp.float32),
        }
        for name, _, cin, cout in vgg_layers("vgg19")[:14]
    }


def progress(line: str) -> None:
    """One progress line on stderr, which the parent passes through: a kernel that runs out
    of time shows how far it got instead of ending with no trace."""
    print(f"[{time.strftime('%H:%M:%S')}] {line}", file=sys.stderr, flush=True)


# scale -> (views (inputs, targets), size (h, w), default kernels); paper: stage 4 of the dl3dv recipe.
SCALES = {"paper": ((32, 8), (544, 960), "cudnn,blockwise"), "cpu": ((2, 1), (64, 96), "blockwise")}


def experiment(scale: str, impl: str, block: tuple[int, int] | None = None):
    """``(experiment, stage)``: the ``dl3dv`` recipe's stage 4 with ``impl`` (and the blockwise
    kernel's ``block``) in every global-attention block; at ``scale="cpu"`` with ``config.tiny()``."""
    exp, stage = paper_stage4_experiment()
    model = exp.model if scale == "paper" else C.for_accelerators(C.tiny())
    return replace(exp, model=C.with_attention(model, impl, block)), stage


def measure(
    impl: str,
    steps: int,
    views: tuple[int, int],
    size: tuple[int, int],
    block: tuple[int, int] | None = None,
    scale: str = "paper",
) -> dict:
    """Compile and run stage 4 with ``impl`` in every global-attention block (own process);
    ``views`` (inputs, targets) and ``size`` (h, w) of every view, ``block`` (the blockwise
    kernel's query and key block) replacing the config's (512, 512)."""
    exp, stage = experiment(scale, impl, block)
    model = exp.model
    b = stage.global_batch // PAPER_STAGE4_DEVICES
    (v, t), (h, w) = views, size
    vgg = perceptual_for_compile(exp)
    runner, optimizer = make_step(exp, stage, vgg)
    params = host_init_params(model)
    state = runner.place_state(T.init_train_state(params, optimizer, jax.random.key(1)))
    host_batches = [synthetic_batch(b, v, t, h, w, seed=i) for i in range(2)]
    batches = [runner.place_batch(x) for x in host_batches]
    # Steps run through the jitted step, not an AOT executable: on jax 0.10.2 (CPU) the
    # executable from ``lower().compile()`` of this donated step returned NaN perceptual
    # losses (the VGG params it closes over came back as garbage) where the jitted call
    # and the undonated executable agree. The first call therefore includes the compile:
    # compile_s = first call - median step. XLA's memory analysis comes from a separate
    # AOT compile after the steps, never executed.
    step = runner.step
    times, metrics = [], None
    progress(f"{impl}: state and batches ready; first call (compile + one step) ...")
    for i in range(steps + 1):  # the first call compiles
        t0 = time.perf_counter()
        state, metrics = step(state, batches[i % 2])
        jax.block_until_ready((state, metrics))
        times.append(time.perf_counter() - t0)
        peak_now = (jax.local_devices()[0].memory_stats() or {}).get("peak_bytes_in_use")
        progress(
            f"{impl}: call {i + 1}/{steps + 1} took {times[-1]:.1f} s"
            + (f", device peak so far {peak_now / GIB:.2f} GiB" if peak_now is not None else "")
        )
    first_s, times = times[0], times[1:]
    stats = jax.local_devices()[0].memory_stats() or {}
    peak, limit = stats.get("peak_bytes_in_use"), stats.get("bytes_limit")
    t0 = time.perf_counter()
    compiled = step.lower(state, batches[0]).compile()
    aot_compile_s = time.perf_counter() - t0
    step_s = float(np.median(times))
    flops = train_step_model_flops(exp, vgg, host_batches[0])
    return {
        "attention_impl": impl,
        "attention_block": [model.backbone.transformer.attention_block_q, model.backbone.transformer.attention_block_k],
        "model": "paper_dl3dv" if scale == "paper" else "tiny",
        "per_device_batch": b,
        "inputs": v,
        "targets": t,
        "size": [h, w],
        "params": count_params(params),
        "bf16": exp.bf16,
        "perceptual_weight": exp.perceptual_weight,
        "first_call_s": first_s,
        "compile_s": first_s - step_s,
        "aot_compile_s": aot_compile_s,
        "memory_analysis": memory_analysis_bytes(compiled),
        "device_peak_bytes_in_use": peak,
        "device_bytes_limit": limit,
        "step_s_median": step_s,
        "step_s_all": times,
        "xla_flops": xla_cost(compiled)["flops"],
        "model_flops": flops,
        **throughput(flops, step_s, jax.devices()[0].device_kind),
        "loss": float(metrics["loss"]),  # pyright: ignore[reportOptionalSubscript] -- the loop above runs at least once
        "splat_dropped": float(metrics["splat_dropped"]),  # pyright: ignore[reportOptionalSubscript] -- as above
        "skipped_total": float(metrics["skipped_total"]),  # non-finite or guarded steps  # pyright: ignore[reportOptionalSubscript] -- as above
    }


def profile_step(
    impl: str, views: tuple[int, int], size: tuple[int, int], block: tuple[int, int] | None = None, scale: str = "paper"
) -> dict:
    """``profile_program`` of one undonated step of :func:`measure`'s program at ``views``
    and ``size`` (one repeat: each traced call of a paper-sized step is seconds and
    hundreds of MB of trace)."""
    from llrmpp_jax.profiling import profile_program

    exp, stage = experiment(scale, impl, block)
    b = stage.global_batch // PAPER_STAGE4_DEVICES
    (v, t), (h, w) = views, size
    runner, optimizer = make_step(exp, stage, perceptual_for_compile(exp), donate=False)
    state = runner.place_state(T.init_train_state(host_init_params(exp.model), optimizer, jax.random.key(1)))
    prof = profile_program(runner.step, (state, runner.place_batch(synthetic_batch(b, v, t, h, w))), repeats=1)
    return {
        "program": "train_step",
        "attention_impl": impl,
        "model": "paper_dl3dv" if scale == "paper" else "tiny",
        "per_device_batch": b,
        "inputs": v,
        "targets": t,
        "size": [h, w],
        "environment": environment(),
        "profile": prof.to_json(),
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=(__doc__ or "").split("\n")[0])
    ap.add_argument("--out", default=os.path.join("runs", "bench", "bench_paper_step.json"), help="JSON file written")
    ap.add_argument("--scale", default="paper", help=f"one of {sorted(SCALES)}: the paper model, or config.tiny()")
    ap.add_argument(
        "--impls",
        default=None,
        help=f"comma-separated attention kernels, each of {ATTENTION_IMPLEMENTATIONS} "
        f"(default: the scale's, {SCALES['paper'][2]} at paper scale)",
    )
    ap.add_argument("--steps", type=int, default=2, help="timed steps per kernel (after one warm-up step)")
    ap.add_argument("--timeout", type=float, default=300.0, help="seconds per kernel (compile and steps)")
    ap.add_argument(
        "--views", default="", help="inputs,targets per scene (default: the scale's, stage 4: 32,8; --profile: 8,8)"
    )
    ap.add_argument("--size", default="", help="HxW of every view (default: the scale's, stage 4: 544x960)")
    ap.add_argument("--block", default="", help="Q,K: the blockwise kernel's query and key block (config: 512,512)")
    ap.add_argument("--profile", action="store_true", help="profile one step of the first kernel instead of timing")
    ap.add_argument("--_impl", help=argparse.SUPPRESS)  # internal: one kernel, in its own process
    args = ap.parse_args()
    if args.scale not in SCALES:
        raise SystemExit(f"--scale: unknown scale {args.scale!r}, expected one of {sorted(SCALES)}")
    scale_views, scale_size, scale_impls = SCALES[args.scale]
    if args.steps < 1:
        raise SystemExit(f"--steps: expected >= 1, got {args.steps}")
    impls = [s for s in (args.impls or scale_impls).split(",") if s]
    for impl in impls:
        if impl not in ATTENTION_IMPLEMENTATIONS:
            raise SystemExit(f"--impls: unknown attention kernel {impl!r}, expected one of {ATTENTION_IMPLEMENTATIONS}")
    try:
        views = (
            tuple(int(x) for x in args.views.split(","))
            if args.views
            else ((8, 8) if args.profile and args.scale == "paper" else scale_views)
        )
        size = tuple(int(x) for x in args.size.lower().split("x")) if args.size else scale_size
        block = tuple(int(x) for x in args.block.split(",")) if args.block else None
        assert len(views) == 2 and len(size) == 2 and min(views + size) >= 1
        assert block is None or (len(block) == 2 and min(block) >= 1)
    except (ValueError, AssertionError):
        raise SystemExit(
            f"--views/--size/--block: expected 'inputs,targets', 'HxW' and 'Q,K' of positive "
            f"integers, got {args.views!r}, {args.size!r} and {args.block!r}"
        ) from None
    try:
        check_case(C.paper_dl3dv() if args.scale == "paper" else C.tiny(), views, *size)
    except ValueError as e:
        raise SystemExit(f"--views/--size: {e}") from None
    if args._impl:
        print(json.dumps(measure(args._impl, args.steps, views, size, block, args.scale)))
        return
    os.makedirs(os.path.dirname(os.path.abspath(args.out)), exist_ok=True)
    if args.profile:
        result = profile_step(impls[0], views, size, block, args.scale)
        print(profile_markdown(result["profile"]))
        with open(args.out, "w") as f:
            json.dump(result, f, indent=1)
        print("wrote", args.out)
        return
    dev = jax.devices()[0]
    result = {
        "benchmark": "paper_step",
        "scale": args.scale,
        "device": str(dev),
        "device_kind": dev.device_kind,
        "platform": dev.platform,
        "jax_version": jax.__version__,
        "xla_flags": os.environ.get("XLA_FLAGS", ""),
        "compilation_cache_dir": os.environ.get("JAX_COMPILATION_CACHE_DIR", ""),
        "paper_a100_step_s": PAPER_A100["train_step_s"],
        "cases": {},
    }
    for impl in impls:
        cmd = [
            sys.executable,
            "-m",
            "llrmpp_jax.benchmarks.paper_step",
            "--_impl",
            impl,
            "--steps",
            str(args.steps),
            "--scale",
            args.scale,
            "--views",
            ",".join(map(str, views)),
            "--size",
            f"{size[0]}x{size[1]}",
            "--block",
            args.block,
        ]
        t0 = time.time()
        try:
            proc = subprocess.run(cmd, stdout=subprocess.PIPE, text=True, timeout=args.timeout)  # stderr: through
            if proc.returncode:
                case = {"failed": f"exit {proc.returncode} (its error and progress are on stderr above)"}
            else:
                case = json.loads(proc.stdout.strip().splitlines()[-1])
        except subprocess.TimeoutExpired:
            case = {"failed": f"timed out after {args.timeout:.0f} s (progress on stderr above)"}
        case["wall_s"] = time.time() - t0  # pyright: ignore[reportArgumentType] -- a JSON row: mixed values
        result["cases"][impl] = case
        print(impl, json.dumps(case), flush=True)
        with open(args.out, "w") as f:  # after every kernel: a later timeout loses nothing
            json.dump(result, f, indent=2)
    print("wrote", args.out)


if __name__ == "__main__":
    main()
