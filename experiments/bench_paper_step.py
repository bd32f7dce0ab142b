"""The paper's stage-4 training step *executed* on one accelerator: compile time, XLA's
memory analysis, the device's peak memory and the step time, per attention kernel.

Run (one GPU or TPU):
    python experiments/bench_paper_step.py --out experiments/results/bench_paper_step.json
    python experiments/bench_paper_step.py --impls blockwise --steps 1     # the portable kernel only

``experiments/bench_train.py`` can only *compile* this step on a CPU (XLA's memory analysis,
no run). Here it runs: ``experiments/dl3dv.py`` stage 4 (32 inputs + 8 targets at 544x960,
one scene per device as in the paper's 64-GPU run, bf16 compute, remat everywhere as
``config.for_accelerators`` sets it, the sequential SSD inter-chunk recurrence, Long-LRM's
VGG19 perceptual term with random weights of its shapes unless the file names weights: the
cost does not depend on the weights), with the project's own step
(``trainer.make_loss_fn`` -> ``train.make_train_step`` -> ``train.pmap_train_step``, donated
state) and the model's parameters initialised as for training.

The batch is synthetic: uniform-noise images (content changes nothing in a step whose shapes
and capacities are static) seen from an orbit of 40 cameras around the origin (radius 2-3 m,
horizontal field of view 50-70 degrees), targets every fifth view, so the Gaussians project
into the targets as in a real capture. Each kernel (``--impls``: ``cudnn`` on NVIDIA GPUs,
``blockwise`` anywhere, ``xla`` is only there to show it does not fit) is measured in its own
process, so its peak memory is its own. Reported per kernel: the first call's seconds
(compile + one step) and the compile's share, ``memory_analysis()`` (as ``bench_train.py``,
from a separate ahead-of-time compile, ``aot_compile_s``), the device's ``peak_bytes_in_use``, the median
of ``--steps`` synced step times after the first call, the last step's loss and splat
overflow (``splat_dropped``), and how many steps the trainer's guard skipped (``skipped_total``).
Set ``JAX_COMPILATION_CACHE_DIR`` (with ``JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS=0``) and
the AOT compile loads the step's executable from the cache (0.4 s on an H200, not 80 s).
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time

import jax
import numpy as np

from llrmpp_jax import config as C
from llrmpp_jax import train as T
from llrmpp_jax.data.camera_paths import orbit_path, pinhole_intrinsics
from llrmpp_jax.model import init_params
from llrmpp_jax.nn.attention import ATTENTION_IMPLEMENTATIONS
from llrmpp_jax.nn.backbone import count_params

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from bench_train import (  # noqa: E402
    PAPER_STAGE4_DEVICES, make_step, memory_analysis_bytes, paper_stage4_experiment, perceptual_for_compile,
)

GIB = 2.0**30


def synthetic_batch(b: int, v: int, t: int, h: int, w: int, seed: int = 0) -> dict[str, np.ndarray]:
    """``b`` scenes of ``v`` inputs and ``t`` targets, ``h`` x ``w``: noise images on an orbit
    of ``v + t`` cameras (every ``(v + t) // t``-th view a target). Shapes as the trainer's
    batches (``[b, views, ...]``, float32)."""
    rng = np.random.default_rng(seed)
    n = v + t
    is_target = np.zeros(n, bool)
    is_target[np.linspace(0, n - 1, t).round().astype(int)] = True
    out: dict[str, list] = {k: [] for k in ("input_images", "input_c2w", "input_intrinsics",
                                            "target_images", "target_c2w", "target_intrinsics")}
    for _ in range(b):
        c2w = orbit_path(rng, n, np.zeros(3), 2.0, 3.0).astype(np.float32)
        intr = pinhole_intrinsics(rng, n, h, w, (50.0, 70.0)).astype(np.float32)
        images = rng.uniform(0, 1, (n, h, w, 3)).astype(np.float32)
        for role, sel in (("input", ~is_target), ("target", is_target)):
            out[f"{role}_images"].append(images[sel])
            out[f"{role}_c2w"].append(c2w[sel])
            out[f"{role}_intrinsics"].append(intr[sel])
    return {k: np.stack(x) for k, x in out.items()}


def progress(line: str) -> None:
    """One progress line on stderr, which the parent passes through: a kernel that runs out
    of time shows how far it got (on an H200 both kernels ran past 165 s with no trace)."""
    print(f"[{time.strftime('%H:%M:%S')}] {line}", file=sys.stderr, flush=True)


def measure(impl: str, steps: int, views: tuple[int, int] | None = None, size: tuple[int, int] | None = None,
            block: tuple[int, int] | None = None) -> dict:
    """Compile and run stage 4 with ``impl`` in every global-attention block (own process);
    ``views`` (inputs, targets), ``size`` (h, w) and ``block`` (the blockwise kernel's query
    and key block) replace the stage's (32, 8), 544x960 and the config's (512, 512)."""
    exp, stage = paper_stage4_experiment()
    model = C.with_attention(exp.model, impl, block)
    exp = C.replace(exp, model=model)
    b = stage.global_batch // PAPER_STAGE4_DEVICES
    h, w = size or (-(-stage.resize_h // model.size_multiple) * model.size_multiple, 960)  # 540 -> 544
    v, t = views or (stage.num_inputs, stage.num_targets)
    step_fn, optimizer = make_step(exp, stage, perceptual_for_compile(exp))
    params = init_params(jax.random.key(0), model, 2, 32, 32)
    state = T.replicate_for_pmap(T.init_train_state(params, optimizer, jax.random.key(1)))
    batches = [T.shard_for_pmap(synthetic_batch(b, v, t, h, w, seed=i)) for i in range(2)]
    # Steps run through the jitted pmap, not an AOT executable: on jax 0.10.2 (CPU) the
    # executable from ``lower().compile()`` of this donated step returned NaN perceptual
    # losses (the VGG params it closes over came back as garbage) where the jitted call
    # and the undonated executable agree. The first call therefore includes the compile:
    # compile_s = first call - median step. XLA's memory analysis comes from a separate
    # AOT compile after the steps, never executed.
    step = T.pmap_train_step(step_fn, donate=True)
    times, metrics = [], None
    progress(f"{impl}: state and batches ready; first call (compile + one step) ...")
    for i in range(steps + 1):  # the first call compiles
        t0 = time.perf_counter()
        state, metrics = step(state, batches[i % 2])
        jax.block_until_ready((state, metrics))
        times.append(time.perf_counter() - t0)
        peak_now = (jax.local_devices()[0].memory_stats() or {}).get("peak_bytes_in_use")
        progress(f"{impl}: call {i + 1}/{steps + 1} took {times[-1]:.1f} s"
                 + (f", device peak so far {peak_now / GIB:.2f} GiB" if peak_now is not None else ""))
    first_s, times = times[0], times[1:]
    stats = jax.local_devices()[0].memory_stats() or {}
    peak, limit = stats.get("peak_bytes_in_use"), stats.get("bytes_limit")
    t0 = time.perf_counter()
    memory = memory_analysis_bytes(step.lower(state, batches[0]).compile())
    aot_compile_s = time.perf_counter() - t0
    return {
        "attention_impl": impl, "attention_block": [model.backbone.transformer.attention_block_q,
                                                    model.backbone.transformer.attention_block_k],
        "per_device_batch": b, "inputs": v, "targets": t, "size": [h, w],
        "params": count_params(params), "bf16": exp.bf16, "perceptual_weight": exp.perceptual_weight,
        "first_call_s": first_s, "compile_s": first_s - float(np.median(times)),
        "aot_compile_s": aot_compile_s, "memory_analysis": memory,
        "device_peak_bytes_in_use": peak, "device_bytes_limit": limit,
        "step_s_median": float(np.median(times)), "step_s_all": times,
        "loss": float(np.asarray(metrics["loss"])[0]),
        "splat_dropped": float(np.asarray(metrics["splat_dropped"])[0]),
        "skipped_total": float(np.asarray(metrics["skipped_total"])[0]),  # non-finite or guarded steps
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--out", default=os.path.join(os.path.dirname(os.path.abspath(__file__)), "results",
                                                  "bench_paper_step.json"), help="JSON file written")
    ap.add_argument("--impls", default="cudnn,blockwise",
                    help=f"comma-separated attention kernels, each of {ATTENTION_IMPLEMENTATIONS}")
    ap.add_argument("--steps", type=int, default=2, help="timed steps per kernel (after one warm-up step)")
    ap.add_argument("--timeout", type=float, default=300.0, help="seconds per kernel (compile and steps)")
    ap.add_argument("--views", default="32,8", help="inputs,targets per scene (stage 4: 32,8)")
    ap.add_argument("--size", default="544x960", help="HxW of every view (stage 4: 544x960)")
    ap.add_argument("--block", default="", help="Q,K: the blockwise kernel's query and key block (config: 512,512)")
    ap.add_argument("--_impl", help=argparse.SUPPRESS)  # internal: one kernel, in its own process
    args = ap.parse_args()
    if args.steps < 1:
        raise SystemExit(f"--steps: expected >= 1, got {args.steps}")
    impls = [s for s in args.impls.split(",") if s]
    for impl in impls:
        if impl not in ATTENTION_IMPLEMENTATIONS:
            raise SystemExit(f"--impls: unknown attention kernel {impl!r}, expected one of {ATTENTION_IMPLEMENTATIONS}")
    try:
        views = tuple(int(x) for x in args.views.split(","))
        size = tuple(int(x) for x in args.size.lower().split("x"))
        block = tuple(int(x) for x in args.block.split(",")) if args.block else None
        assert len(views) == 2 and len(size) == 2 and min(views + size) >= 1
        assert block is None or (len(block) == 2 and min(block) >= 1)
    except (ValueError, AssertionError):
        raise SystemExit(f"--views/--size/--block: expected 'inputs,targets', 'HxW' and 'Q,K' of positive "
                         f"integers, got {args.views!r}, {args.size!r} and {args.block!r}") from None
    if args._impl:
        print(json.dumps(measure(args._impl, args.steps, views, size, block)))
        return
    dev = jax.devices()[0]
    result = {"benchmark": "paper_step", "device": str(dev), "device_kind": dev.device_kind,
              "platform": dev.platform, "jax_version": jax.__version__,
              "xla_flags": os.environ.get("XLA_FLAGS", ""),
              "compilation_cache_dir": os.environ.get("JAX_COMPILATION_CACHE_DIR", ""), "cases": {}}
    for impl in impls:
        cmd = [sys.executable, os.path.abspath(__file__), "--_impl", impl, "--steps", str(args.steps),
               "--views", args.views, "--size", args.size, "--block", args.block]
        t0 = time.time()
        try:
            proc = subprocess.run(cmd, stdout=subprocess.PIPE, text=True, timeout=args.timeout)  # stderr: through
            if proc.returncode:
                case = {"failed": f"exit {proc.returncode} (its error and progress are on stderr above)"}
            else:
                case = json.loads(proc.stdout.strip().splitlines()[-1])
        except subprocess.TimeoutExpired:
            case = {"failed": f"timed out after {args.timeout:.0f} s (progress on stderr above)"}
        case["wall_s"] = time.time() - t0
        result["cases"][impl] = case
        print(impl, json.dumps(case), flush=True)
        os.makedirs(os.path.dirname(os.path.abspath(args.out)), exist_ok=True)
        with open(args.out, "w") as f:  # after every kernel: a later timeout loses nothing
            json.dump(result, f, indent=2)
    print("wrote", args.out)


if __name__ == "__main__":
    main()
