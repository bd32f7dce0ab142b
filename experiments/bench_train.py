"""Training-step time and memory on this machine, and XLA's memory analysis of the paper's
stage-4 step, written as JSON.

1. **Measured cases** (this machine), each in a fresh subprocess so that the process's
   max RSS belongs to that case alone:

   * ``demo`` -- the ``demo`` recipe as it trains (64x64, 4 inputs, 2 targets,
     global batch 2, float32, MSE only).
   * ``mid_<size>`` -- the paper architecture shrunk (``config.paper_dl3dv()`` with
     D = 256, d_state 64, 8 blocks ``{1T3M}x2``, decoder width 128; K = 16, F = 32, S = 2,
     ``LLGGG`` as in the paper), DL3DV stage 1's views (8 inputs; ``--mid-sizes``,
     default 256 as stage 1 and 192) with 4 targets, batch 1, float32, **perceptual
     weight 0** (the VGG term is left out to keep the CPU run short; its cost does not
     depend on the model).

   At 256x256 the backbone's two global-attention blocks see L = 8,194 tokens. The XLA
   attention path materialised ``[4, L, L]`` float32 logits (1.07 GB each, dozens of them
   live in the backward): XLA's peak was ~17.2 GiB with or without remat (rows
   ``*_xla_attention``). With the blockwise kernel (now the default) the peak was 12.1 GiB
   (12.2 with remat), no longer attention-bound: XLA's buffer live ranges showed the
   Mamba2 blocks' ``[chunks, heads, Q, Q]`` intra-chunk scores (now computed a chunk group
   at a time and recomputed in the backward, ``nn/ssd.py``) and, with remat, the
   recomputed activations of *all* six Mamba2 blocks alive at once during the decoder's
   backward: XLA:CPU's default concurrency-optimised scheduler runs the recomputations
   early. This script therefore compiles with the memory-minimising scheduler
   (``CPU_MEMORY_SCHEDULER``); ``mid_256_remat`` then needs 4.6 GiB and runs. A case whose
   XLA peak exceeds ``--max-step-gb`` (default 12) is compiled and analysed but its steps
   are not run (``steps_run`` says why).

   Every case runs with and without remat (``jax.checkpoint`` of every backbone and decoder
   block). The step is the project's own: ``objective.make_loss_fn`` ->
   ``train.make_train_step`` -> the runner (``trainer.stage_runner``: jit over a mesh of
   1 device, donated state), on
   procedural batches from ``data.BatchIterator``. Reported: compile time
   (``lower().compile()``), XLA's ``memory_analysis()`` of the compiled step (argument,
   output, alias and temp bytes; ``xla_total_bytes`` = temp + argument + output, which
   counts the donated state -- the alias bytes -- twice, so ``xla_peak_bytes`` = total -
   alias is given too), the process max RSS after the timed steps, the device's
   ``peak_bytes_in_use`` where the backend reports it (GPU/TPU; ``None`` on CPU), and the
   median wall time of ``--steps`` steps after one untimed warm-up step, each on a new
   batch (prefetched, so data time is not included) with ``block_until_ready``.

2. **Paper stage 4** (the ``dl3dv`` recipe's stage 4: 32 inputs + 8 targets at 544x960,
   the paper's global batch 64 on 64 GPUs, so 1 scene per device; bf16 compute and
   backbone remat as the experiment file sets; the perceptual term as the file sets it,
   Long-LRM's VGG19, with random weights of its shapes unless the file names weights): the per-device step is
   lowered from ``jax.ShapeDtypeStruct``s (nothing allocated) and compiled for CPU in a subprocess
   with a time limit (``--paper-timeout``, default 600 s: lowering + compiling took 2-5
   min on the busy 2-core box) and an RSS guard
   (``--paper-max-rss-gb``). If it compiles, XLA's memory analysis is reported
   (``"source": "xla_compiled_cpu"``). Always reported beside it: an **estimate** from
   ``jax.eval_shape`` (parameter, gradient and AdamW bytes, and the sizes of the main
   activations), labelled ``"estimate"``. The experiment file sets
   ``config.for_accelerators``, which picks the cuDNN flash kernel on GPU and the pure-JAX
   blockwise kernel elsewhere, with remat in the backbone and the decoder: compiled on CPU,
   the step therefore uses blockwise attention, and XLA's number is the memory of the step
   as it runs without cuDNN (the plain XLA path would hold ``[heads, L, L]`` logits, 1.6 TB
   per block at L = 261,122 in bf16; ``transformer_attention_logits_xla_per_block``).

Usage: ``python experiments/bench_train.py [--out PATH] [--quick] [--skip-paper]
[--steps N] [--mid-sizes 256,192] [--max-step-gb G] [--max-rss-gb G] [--paper-timeout S]
[--paper-max-rss-gb G] [--paper-only] [--paper-note TEXT] [--paper-dump DIR]``. ``--quick``:
the demo config only (with and without remat). ``--paper-only``: the stage-4 analysis
alone, replacing ``paper_stage4`` in the existing ``--out`` file (the previous entry is
appended to ``paper_stage4_history``); ``--paper-dump DIR``: also dump XLA's compile there
and store its peak breakdown (``peak_breakdown``: the values alive at the peak as a tree
of (depth, op name, bytes), a loop's row being its body's peak).
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import re
import resource
import subprocess
import sys
import time
from dataclasses import replace

import jax
import jax.numpy as jnp
import numpy as np
import psutil

from llrmpp_jax import config as C
from llrmpp_jax import train as T
from llrmpp_jax.benchmarks.measure import memory_analysis_bytes
from llrmpp_jax.benchmarks.paper_step import (
    PAPER_STAGE4_DEVICES,
    make_step,
    paper_stage4_experiment,
    perceptual_for_compile,
)
from llrmpp_jax.data import BatchIterator, ProceduralConfig, ProceduralSource
from llrmpp_jax.experiment import DataConfig, ExperimentConfig, StageConfig, load_experiment
from llrmpp_jax.experiment_data import batch_config
from llrmpp_jax.model import init_params, reconstruct
from llrmpp_jax.nn.backbone import count_params, parse_block_pattern

HERE = os.path.dirname(os.path.abspath(__file__))
GIB = 2.0**30


def demo_experiment() -> ExperimentConfig:
    """The ``demo`` recipe unchanged."""
    return load_experiment("demo")


def mid_experiment(size: int = 256) -> ExperimentConfig:
    """DL3DV stage 1's views (8 inputs, ``size`` x ``size``; the stage's own is 256) on a
    D = 256, 8-block paper-shaped model, 4 targets, batch 1, float32, no perceptual term,
    procedural scenes."""
    base = load_experiment("dl3dv")
    paper = C.paper_dl3dv()
    model = replace(
        paper,
        backbone=replace(
            paper.backbone,
            dims=(256,),
            pattern="{1T3M}x2",
            num_layers=8,
            mamba=replace(paper.backbone.mamba, d_state=64),
        ),
        decoder=replace(paper.decoder, dim=128),
    )
    stage = replace(
        base.stages[0], name=f"mid_{size}", global_batch=1, num_targets=4, resize_h=size, min_span=None, max_span=None
    )
    data = DataConfig(procedural=ProceduralConfig(height=size, width=size, num_frames=16))
    return replace(base, name=f"mid_{size}", model=model, stages=(stage,), data=data, perceptual_weight=0.0, bf16=False)


def with_remat(model: C.ModelConfig) -> C.ModelConfig:
    """Remat every backbone and decoder block."""
    return replace(model, backbone=replace(model.backbone, remat=True), decoder=replace(model.decoder, remat=True))


# XLA:CPU's default concurrency-optimised scheduler runs every remat'd block's recomputation
# early in the backward pass (XLA:CPU drops jax.checkpoint's optimisation barriers before
# scheduling), so all blocks' recomputed activations are alive at once and remat saves
# nothing (mid_256 with remat: 9.3 GB temp; 4.8 GB with the memory-minimising scheduler).
# Set for this process and the measured cases (children inherit it); other backends ignore it.
CPU_MEMORY_SCHEDULER = "--xla_cpu_enable_concurrency_optimized_scheduler=false"


def _max_rss_bytes() -> int:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024  # Linux reports KiB


def case_experiment(name: str) -> ExperimentConfig:
    """``"demo"``, ``"small"`` (the ``small`` recipe, the shipped model's) or ``"mid_<size>"``."""
    if name == "demo":
        return demo_experiment()
    if name == "small":
        return load_experiment("small")
    if name.startswith("mid_") and name[4:].isdigit():
        return mid_experiment(int(name[4:]))
    raise ValueError(f"unknown case {name!r}, expected 'demo', 'small' or 'mid_<size>'")


def measure_case(name: str, remat: bool, steps: int, max_step_bytes: float) -> dict:
    """Compile, memory and step time of one case (run inside its own process). Steps run
    only when XLA's peak (``xla_peak_bytes``) is at most ``max_step_bytes``."""
    exp = case_experiment(name)
    if remat:
        exp = replace(exp, model=with_remat(exp.model))
    stage = exp.stages[0]
    h, w = stage.resize_h, stage.resize_w or stage.resize_h
    bcfg = batch_config(exp, stage)
    it = BatchIterator(ProceduralSource(exp.data.procedural), bcfg, seed=0, num_workers=1)
    t0 = time.perf_counter()
    host_batches = [next(it) for _ in range(steps + 1)]
    it.close()
    data_s = (time.perf_counter() - t0) / (steps + 1)
    runner, optimizer = make_step(exp, stage, None)
    batches = [runner.place_batch(b) for b in host_batches]
    params = init_params(jax.random.key(0), exp.model, stage.num_inputs, h, w)  # pyright: ignore[reportArgumentType] -- the stage sets resize_h
    state = runner.place_state(T.init_train_state(params, optimizer, jax.random.key(1)))
    t0 = time.perf_counter()
    compiled = runner.step.lower(state, batches[0]).compile()
    compile_s = time.perf_counter() - t0
    memory = memory_analysis_bytes(compiled)
    times, metrics = [], None
    if memory["xla_peak_bytes"] > max_step_bytes:
        batches = []  # too large for this machine: compile-time analysis only
    for i, batch in enumerate(batches):
        t0 = time.perf_counter()
        state, metrics = compiled(state, batch)
        jax.block_until_ready((state, metrics))
        if i:  # the first call is a warm-up
            times.append(time.perf_counter() - t0)
    dev_stats = jax.local_devices()[0].memory_stats() or {}
    ran = metrics is not None
    return {
        "experiment": exp.name,
        "remat": remat,
        "dtype": "bfloat16" if exp.bf16 else "float32",
        "perceptual_weight": exp.perceptual_weight,
        "batch": stage.global_batch,
        "inputs": stage.num_inputs,
        "targets": stage.num_targets,
        "size": [h, w],
        "model": {
            "dims": list(exp.model.backbone.dims),
            "pattern": exp.model.backbone.pattern,
            "num_layers": exp.model.backbone.num_layers,
            "d_state": exp.model.backbone.mamba.d_state,
            "K": exp.model.head.gaussians_per_token,
            "F": exp.model.head.feature_dim,
            "decoder": exp.model.decoder.blocks,
            "decoder_dim": exp.model.decoder.dim,
            "partitions": exp.model.decoder.partitions,
            "params": count_params(params),
        },
        "data_s_per_batch": data_s,
        "compile_s": compile_s,
        "steps_run": ran
        if ran
        else (f"no: XLA peak {memory['xla_peak_bytes'] / GIB:.1f} GiB > --max-step-gb {max_step_bytes / GIB:.1f}"),
        "step_s_median": float(np.median(times)) if ran else None,
        "step_s_all": times,
        "memory_analysis": memory,
        "max_rss_bytes": _max_rss_bytes(),
        "device_peak_bytes_in_use": dev_stats.get("peak_bytes_in_use"),
        "final_loss": float(metrics["loss"]) if ran else None,
        "splat_dropped": float(metrics["splat_dropped"]) if ran else None,
    }


def paper_abstract_args(exp: ExperimentConfig, stage: StageConfig, vgg_params: dict | None):
    """Stage 4's step on one device (the runner's jitted step, closing over ``vgg_params``)
    and its inputs as ShapeDtypeStructs (state, batch ``[b, ...]``): ``(step, state, batch,
    (b, v, t, h, w))``."""
    if stage.global_batch % PAPER_STAGE4_DEVICES:
        raise ValueError(
            f"stage {stage.name}: global_batch {stage.global_batch} does not split over {PAPER_STAGE4_DEVICES} devices"
        )
    b = stage.global_batch // PAPER_STAGE4_DEVICES
    h = -(-stage.resize_h // exp.model.size_multiple) * exp.model.size_multiple  # 540 -> 544  # pyright: ignore[reportOptionalOperand] -- the paper stage sets resize_h
    w = 960
    v, t = stage.num_inputs, stage.num_targets
    params = jax.eval_shape(lambda k: init_params(k, exp.model, 2, 32, 32), jax.random.key(0))
    runner, optimizer = make_step(exp, stage, vgg_params)
    state = jax.eval_shape(lambda p: T.init_train_state(p, optimizer, jax.random.key(1)), params)
    f32 = lambda *s: jax.ShapeDtypeStruct((b,) + s, jnp.float32)  # noqa: E731
    batch = {
        "input_images": f32(v, h, w, 3),
        "input_c2w": f32(v, 4, 4),
        "input_intrinsics": f32(v, 4),
        "target_images": f32(t, h, w, 3),
        "target_c2w": f32(t, 4, 4),
        "target_intrinsics": f32(t, 4),
    }
    if "depth" in exp.model.outputs:
        batch["target_depth"] = f32(t, h, w)
    return runner.step, state, batch, (b, v, t, h, w)


def compile_paper() -> dict:
    """Lower and compile the stage-4 per-device step for CPU (run inside its own process)."""
    exp, stage = paper_stage4_experiment()
    step, state, batch, _ = paper_abstract_args(exp, stage, perceptual_for_compile(exp))
    t0 = time.perf_counter()
    lowered = step.lower(state, batch)
    lower_s = time.perf_counter() - t0
    t0 = time.perf_counter()
    compiled = lowered.compile()
    return {
        "source": "xla_compiled_cpu",
        "lower_s": lower_s,
        "compile_s": time.perf_counter() - t0,
        "memory_analysis": memory_analysis_bytes(compiled),
        "max_rss_bytes": _max_rss_bytes(),
    }


_BREAKDOWN = re.compile(r"^(?P<indent>[\s│]*)[├└]── (?P<name>\S+) \([\d.]+%, total: (?P<total>[\d ]+) bytes")
_SHORT = (
    ("jit(_fun)/transpose(jvp(LongLRMPP.reconstruct))", "bwd(reconstruct)"),
    ("jit(_fun)/transpose(jvp(LongLRMPP.render))", "bwd(render)"),
    ("jit(_fun)/jvp(LongLRMPP.reconstruct)", "fwd(reconstruct)"),
    ("jit(_fun)/jvp(LongLRMPP.render)", "fwd(render)"),
)


def peak_breakdown(dump_dir: str, min_bytes: float = 1e9) -> dict:
    """XLA's "Stack trace breakdown for peak usage" of the largest compiled module in an
    ``--xla_dump_to`` folder (its ``*live-range.txt``): the values alive at the peak, as a
    tree of (depth, op name, bytes) rows -- a loop's row is its body's peak -- keeping the
    rows of at least ``min_bytes``."""
    path = max(
        (os.path.join(dump_dir, f) for f in os.listdir(dump_dir) if f.endswith("live-range.txt")), key=os.path.getsize
    )
    with open(path) as f:
        lines = f.read().split("Stack trace breakdown for peak usage: ", 1)[1].splitlines()
    rows = []
    for line in lines[2:]:  # lines[1] is the entry computation (the whole peak)
        m = _BREAKDOWN.match(line)
        if m is None:
            break
        total = int(m["total"].replace(" ", ""))
        if total >= min_bytes:
            name = m["name"]
            for long, short in _SHORT:
                name = name.replace(long, short)
            rows.append([len(m["indent"]) // 4, name, total])
    return {
        "source": f"XLA live-range dump ({os.path.basename(path)}), values alive at the peak",
        "peak_bytes": int(lines[0].split(" bytes")[0].replace(" ", "")),
        "rows_depth_name_bytes": rows,
    }


def _nbytes(tree) -> int:
    return int(sum(np.prod(x.shape) * jnp.dtype(x.dtype).itemsize for x in jax.tree.leaves(tree)))


def paper_estimate() -> dict:
    """``jax.eval_shape``-based sizes of the stage-4 per-device step (an estimate, not XLA's)."""
    exp, stage = paper_stage4_experiment()
    cfg = exp.model
    _, state, batch, (b, v, t, h, w) = paper_abstract_args(exp, stage, None)
    cdt = jnp.dtype(jnp.bfloat16 if exp.bf16 else jnp.float32).itemsize
    params = state.params
    n_params = count_params(params)
    adam = _nbytes(state.opt_state)
    gauss = jax.eval_shape(
        lambda p, i, c, k: reconstruct(p, cfg, i, c, k),
        params,
        batch["input_images"],
        batch["input_c2w"],
        batch["input_intrinsics"],
    )
    n_gauss = int(gauss.means.shape[1])
    d = cfg.backbone.dims[0]
    m = cfg.backbone.mamba
    di, nh_m = m.d_inner(d), m.nheads(d)
    seq = v * (h // cfg.patch_size) * (w // cfg.patch_size) + cfg.backbone.num_global_tokens
    layout = parse_block_pattern(cfg.backbone.pattern, "TM", cfg.backbone.num_layers)
    heads = d // cfg.backbone.transformer.head_dim
    r, s, e = cfg.decoder.canvas_ratio, cfg.decoder.partitions, cfg.decoder.dim
    ch, cw = h // r, w // r
    dec_tokens = (h // cfg.decoder.token_stride) * (w // cfg.decoder.token_stride)
    dec_heads = e // cfg.decoder.transformer.head_dim
    capacity = cfg.splat.capacity(n_gauss, ch, cw)
    state_bytes = {
        "params_fp32": 4 * n_params,
        "grads_fp32": 4 * n_params,
        "adamw_state": adam,
        "params_compute_copy": cdt * n_params if exp.bf16 else 0,
    }
    acts = {
        "batch_inputs": _nbytes(batch),
        "backbone_residuals_saved": (b * cfg.backbone.num_layers * seq * d * cdt if cfg.backbone.remat else None),
        "backbone_block_stream": b * seq * d * cdt,
        "mamba_in_proj_out_per_direction": b * seq * (2 * di + 2 * m.ngroups * m.d_state + nh_m) * cdt,
        "mamba_ssd_state_per_chunk_per_direction": (b * (seq // m.chunk_size + 1) * nh_m * m.headdim * m.d_state * 4),
        "transformer_attention_logits_xla_per_block": b * heads * seq * seq * cdt,
        "transformer_mlp_hidden_per_block": b * seq * d * cfg.backbone.transformer.mlp_ratio * cdt,
        "gaussians": _nbytes(gauss),
        "splat_intersection_buffer": b * t * s * capacity * 12,
        "canvas": b * t * s * ch * cw * (cfg.head.feature_dim + 6) * cdt,
        "decoder_stream_per_block": b * t * s * dec_tokens * e * cdt,
        "decoder_global_logits_per_G_block": b * t * s * dec_heads * dec_tokens * dec_tokens * cdt,
        "decoder_local_logits_per_L_block": b * t * s * dec_heads * dec_tokens * cfg.decoder.num_neighbours * cdt,
        "decoder_local_gathered_keys_per_L_block": b * t * s * dec_tokens * cfg.decoder.num_neighbours * e * cdt,
        "rendered_rgb": b * t * h * w * 3 * 4,
    }
    n_t = layout.count("T")
    n_g, n_l = cfg.decoder.blocks.upper().count("G"), cfg.decoder.blocks.upper().count("L")
    mlp = cfg.decoder.transformer.mlp_ratio
    # Tensors live together at the peak of the backward: the whole train state, the batch,
    # what the forward kept (remat'd backbone: block inputs; decoder without remat: every
    # block's q, k, v, attention output and MLP hidden, its logits and probabilities, the
    # L blocks' gathered keys and values) and one recomputed Mamba block (in_proj outputs
    # of both directions).
    terms = {
        "train_state": sum(state_bytes.values()),
        "batch": acts["batch_inputs"],
        "backbone_saved": acts["backbone_residuals_saved"] or 0,
        "one_mamba_block_recomputed": 2 * acts["mamba_in_proj_out_per_direction"],
        "gaussians": acts["gaussians"],
        "splat": acts["splat_intersection_buffer"] + acts["canvas"],
        "decoder_saved": 0
        if cfg.decoder.remat
        else (
            len(cfg.decoder.blocks) * (4 + mlp) * acts["decoder_stream_per_block"]
            + n_g * 2 * acts["decoder_global_logits_per_G_block"]
            + n_l * (2 * acts["decoder_local_logits_per_L_block"] + 2 * acts["decoder_local_gathered_keys_per_L_block"])
        ),
    }
    return {
        "source": "estimate (jax.eval_shape sizes + analytic activation sizes; not XLA's analysis)",
        "per_device_batch": b,
        "inputs": v,
        "targets": t,
        "size": [h, w],
        "dtype": "bfloat16 compute, float32 params/optimizer" if exp.bf16 else "float32",
        "backbone_remat": cfg.backbone.remat,
        "decoder_remat": cfg.decoder.remat,
        "attention_impl": {
            "backbone": cfg.backbone.transformer.attention_impl,
            "decoder": cfg.decoder.transformer.attention_impl,
        },
        "perceptual_weight": exp.perceptual_weight,
        "params": n_params,
        "backbone_tokens": seq,
        "gaussians": n_gauss,
        "splat_capacity": capacity,
        "transformer_blocks": n_t,
        "state_bytes": state_bytes,
        "activation_bytes": acts,
        "estimate_terms": terms,
        "estimate_bytes_without_backbone_attention_logits": int(sum(terms.values())),
        "note": (
            "estimate_terms: tensors live together at the peak of the backward (see the code's "
            "comment); the XLA attention path (attention_impl 'xla') adds "
            "transformer_attention_logits_xla_per_block (x2-3: logits, probabilities, their "
            "gradient) on top, the blockwise and cuDNN kernels only O(L) buffers (see "
            "bench_attention.json); the perceptual term's VGG16 activations (8 targets x 2 "
            "images at 544x960) are not counted"
        ),
    }


def _watch(cmd: list[str], timeout: float, max_rss: float) -> tuple[dict | None, str]:
    """Run ``cmd`` (prints one JSON line last); kill it past ``timeout`` s or ``max_rss`` bytes."""
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    ps = psutil.Process(proc.pid)
    t0, peak, why = time.time(), 0, None
    while proc.poll() is None:
        try:
            peak = max(peak, ps.memory_info().rss)
        except psutil.NoSuchProcess:
            break
        if time.time() - t0 > timeout:
            why = f"timed out after {timeout:.0f} s"
        elif peak > max_rss:
            why = f"RSS above {max_rss / GIB:.1f} GiB"
        if why:
            proc.kill()
            proc.wait()
            break
        time.sleep(0.5)
    out, err = proc.communicate()
    if why:
        return None, why
    if proc.returncode:
        return None, f"exit {proc.returncode}: {err.strip().splitlines()[-1] if err.strip() else ''}"
    return json.loads(out.strip().splitlines()[-1]), f"ok in {time.time() - t0:.0f} s"


def paper_stage4(args: argparse.Namespace) -> dict:
    """Stage 4's estimate and XLA compile (in a watched subprocess), with the peak breakdown
    when ``--paper-dump`` is given."""
    est = paper_estimate()
    env_flags = os.environ.get("XLA_FLAGS", "")
    if args.paper_dump:
        os.environ["XLA_FLAGS"] = (
            f"{env_flags} --xla_dump_to={args.paper_dump} --xla_dump_hlo_pass_re=NONE --xla_dump_hlo_module_re=.*fun.*"
        )
    try:
        res, why = _watch(
            [sys.executable, os.path.abspath(__file__), "--_paper"], args.paper_timeout, args.paper_max_rss_gb * GIB
        )
    finally:
        os.environ["XLA_FLAGS"] = env_flags
    out = {
        "compiled": res if res is not None else {"failed": why},
        "estimate": est,
        "compile_attempt": why,
        "xla_cpu_scheduler": "memory-minimising (--xla_cpu_enable_concurrency_optimized_scheduler=false)",
        "changes": args.paper_note,
    }
    if args.paper_dump and res is not None:
        out["peak_breakdown"] = peak_breakdown(args.paper_dump)
    print("paper_stage4", why, json.dumps(out, indent=1), flush=True)
    return out


def main() -> None:
    if CPU_MEMORY_SCHEDULER not in os.environ.get("XLA_FLAGS", ""):  # before the backend starts
        os.environ["XLA_FLAGS"] = f"{os.environ.get('XLA_FLAGS', '')} {CPU_MEMORY_SCHEDULER}".strip()
    ap = argparse.ArgumentParser(description=(__doc__ or "").split("\n")[0])
    ap.add_argument("--out", default=os.path.join(HERE, "results", "bench_train.json"))
    ap.add_argument("--quick", action="store_true", help="demo config only")
    ap.add_argument("--skip-paper", action="store_true", help="skip the stage-4 analysis")
    ap.add_argument("--steps", type=int, default=3, help="timed steps per case (after one warm-up)")
    ap.add_argument("--mid-sizes", default="256,192", help="image sides of the mid cases")
    ap.add_argument(
        "--max-step-gb",
        type=float,
        default=12.0,
        help="run steps only when XLA's peak of the step is at most this (GiB)",
    )
    ap.add_argument("--case-timeout", type=float, default=1800.0)
    ap.add_argument("--max-rss-gb", type=float, default=16.0, help="kill a measured case above this RSS")
    ap.add_argument("--paper-timeout", type=float, default=600.0)
    ap.add_argument("--paper-max-rss-gb", type=float, default=12.0)
    ap.add_argument(
        "--paper-only",
        action="store_true",
        help="only the stage-4 analysis: replace paper_stage4 in the existing --out file, the "
        "previous entry moving to paper_stage4_history",
    )
    ap.add_argument("--paper-note", default="", help="what changed since the previous stage-4 entry (stored)")
    ap.add_argument(
        "--paper-dump", default=None, help="folder for XLA's dump of the stage-4 compile; its peak breakdown is stored"
    )
    ap.add_argument("--_case", help=argparse.SUPPRESS)  # internal: name:remat, one measured case
    ap.add_argument("--_paper", action="store_true", help=argparse.SUPPRESS)  # internal: compile stage 4
    args = ap.parse_args()
    if args.steps < 1:
        raise ValueError(f"--steps must be >= 1, got {args.steps}")
    if args._case:
        name, remat = args._case.split(":")
        print(json.dumps(measure_case(name, remat == "1", args.steps, args.max_step_gb * GIB)))
        return
    if args._paper:
        print(json.dumps(compile_paper()))
        return

    if args.paper_only:
        with open(args.out) as f:
            result = json.load(f)
        previous = result.pop("paper_stage4", None)
        if previous is not None:
            result.setdefault("paper_stage4_history", []).append(previous)
        result["paper_stage4"] = paper_stage4(args)
        with open(args.out, "w") as f:
            json.dump(result, f, indent=2)
        print("wrote", args.out)
        return

    dev = jax.devices()[0]
    result = {
        "benchmark": "train",
        "device": str(dev),
        "platform": dev.platform,
        "host": platform.machine(),
        "cpu_count": os.cpu_count(),
        "jax_version": jax.__version__,
        "load_average_at_start": list(os.getloadavg()),
        "steps_timed": args.steps,
        "cases": {},
    }
    me = [sys.executable, os.path.abspath(__file__), "--steps", str(args.steps), "--max-step-gb", str(args.max_step_gb)]
    mids = [] if args.quick else [f"mid_{int(s)}" for s in args.mid_sizes.split(",") if s]
    for name in ["demo", *mids]:
        for remat in (False, True):
            key = f"{name}{'_remat' if remat else ''}"
            res, why = _watch(me + ["--_case", f"{name}:{int(remat)}"], args.case_timeout, args.max_rss_gb * GIB)
            result["cases"][key] = res if res is not None else {"failed": why}
            print(key, why, json.dumps(res), flush=True)
    if not args.skip_paper:
        result["paper_stage4"] = paper_stage4(args)
    result["load_average_at_end"] = list(os.getloadavg())
    os.makedirs(os.path.dirname(os.path.abspath(args.out)), exist_ok=True)
    with open(args.out, "w") as f:
        json.dump(result, f, indent=2)
    print("wrote", args.out)


if __name__ == "__main__":
    main()
