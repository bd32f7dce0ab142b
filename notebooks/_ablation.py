"""Shared machinery of the ablation notebooks (paper Tables 4-7).

A notebook lists its table's rows as :class:`Variant` s (row labels, a function that
turns the scale's base :class:`~llrmpp_jax.config.ModelConfig` into the row's config,
and the paper's numbers) and the paper's orderings as :class:`Ordering` s, then calls
:func:`run_table`: every runnable row is trained on procedural scenes with :func:`train`
once per seed, scored on held-out procedural scenes with :func:`evaluate` and timed with
:func:`time_model`; :func:`references` scores the untrained chosen row and the two
baselines (mean colour, nearest input view) on the same scenes. :func:`compare` turns the
per-seed scores into paired differences with 95% intervals and a verdict per ordering,
:func:`format_table` / :func:`format_orderings` print them next to the paper's numbers,
:func:`plot` draws them and :func:`save` writes everything as JSON with the commit.

Three scales (:func:`make_scale`):

* ``"smoke"``: a tiny model (:func:`llrmpp_jax.config.tiny` with a Gaussian head sized for
  procedural rooms) at 32x32, 2 input views, 40 steps, 1 seed, MSE loss only, no LPIPS.
  The numbers only show that the pipeline runs. CI runs this scale.
  Both small scales keep the procedural rooms' world units (no per-window rescaling) with
  Gaussians that reach :data:`PROCEDURAL_MAX_DIST` along their rays.
* ``"cpu"``: the demo model (the ``demo`` recipe: a 64-wide ``{4T}`` backbone, LeCun
  head and decoder init) with each table's K, F, canvas, decoder blocks and S, at 64x64 with
  4 input and 2 target views from windows of 6-10 frames of 16-frame paths (held out:
  8-frame windows), as the ``demo`` recipe trains and evaluates, batch 2,
  :data:`CPU_STEPS` steps (Table 7: 800), 3 seeds (5 for Table 6), 16
  held-out scenes with LPIPS. The budget is the pilot's (``notebooks/_pilot.py``, figures in
  ``notebooks/README.md``). The trainings run
  on one single-core worker process per core (:attr:`Scale.workers`, :func:`run_table`).
* ``"paper"``: the paper's architecture (:func:`paper_dl3dv` / :func:`paper_scannet`) at
  256x256 with the table's view count, MSE + 0.5 perceptual loss, LPIPS, 3 seeds; meant for
  accelerators. The data are still procedural scenes (swap ``source`` for a
  ``FileSource`` of DL3DV / ScanNet scenes to approach the paper's setting).

Environment overrides: ``LLRMPP_NOTEBOOK_SCALE`` (smoke / cpu / paper),
``LLRMPP_NOTEBOOK_STEPS`` the number of train steps, ``LLRMPP_NOTEBOOK_SEEDS`` the seeds
per row, ``LLRMPP_NOTEBOOK_WORKERS`` the trainings run at once (:attr:`Scale.workers`),
``LLRMPP_NOTEBOOK_ROWS`` a comma-separated list of row indices to run (the others
are left out of the results; ``none`` runs no row), ``LLRMPP_NOTEBOOK_OUT`` the folder
:func:`save` writes to (default ``experiments/results/ablations``).
"""

from __future__ import annotations

import contextlib
import dataclasses
import functools
import json
import multiprocessing
import os
import platform
import subprocess
import sys
import time
import types
from collections.abc import Callable, Iterator, Sequence
from concurrent.futures import ProcessPoolExecutor, as_completed
from dataclasses import dataclass
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
from scipy import stats

from llrmpp_jax import config as C
from llrmpp_jax.data import (
    BatchConfig,
    BatchIterator,
    ProceduralConfig,
    ProceduralSource,
    ViewGeometry,
    eval_views,
    make_sample,
    procedural_scene,
    training_views,
)
from llrmpp_jax.evaluate import baseline_predictions
from llrmpp_jax.experiment import load_experiment
from llrmpp_jax.metrics import depth_metrics, load_lpips_params, lpips, psnr, ssim
from llrmpp_jax.model import init_params, reconstruct, render
from llrmpp_jax.nn.backbone import count_params
from llrmpp_jax.objective import LossWeights, make_objective
from llrmpp_jax.perceptual import load_vgg16_lpips
from llrmpp_jax import train as T
from llrmpp_jax.train.loop import StepInfo, run_stage

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
TRAIN_SCENES = 100_000  # training seeds are [0, TRAIN_SCENES)
EVAL_SEED = 1_000_000  # held-out seeds start here (disjoint from training)
SCALES = ("smoke", "cpu", "paper")
CPU_STEPS = 400  # the cpu scale's budget, from the pilot (notebooks/README.md)
CPU_WORKERS = 4  # at most this many single-core trainings at once at the cpu scale (memory)
# Every table at the smoke and cpu scales keeps the procedural rooms' world units
# (Scale.rescale False). Long-LRM's per-window rescaling (input cameras into [-1, 1]^3) gives
# the cpu scale's short windows depth scales that differ ~3x (a sample's mean log depth: sd
# 1.1 around 1.6), and at that spread the depth head learned nothing in 1,200 steps; in world
# units the sd is 0.27 (notebooks/README.md, "Depth (Table 7)"). Where the depth head starts
# (DecoderConfig.depth_bias, depth tables): the mean log target depth of those windows in
# world units, 1.05 / 1.01 / 1.08 over three draws of 128 samples (about 2.9 units).
PROCEDURAL_DEPTH_BIAS = 1.05
# The Gaussian head's distance range in those world units (GaussianHeadConfig.max_dist; the
# cpu base's 3 was chosen on rescaled rooms, where 57% of the target depths lie beyond it):
# 99% of the training windows' target pixels lie within 10 units along their rays (z-depth
# 99th percentile 7.2, corner rays 1.41x longer at this field of view). With 3, 54% of the
# held-out depths were out of the colour Gaussians' reach, and Table 7's colour row could not
# place them (commit fa33438: Abs Diff 1.04, the same to +-0.003 over seeds).
PROCEDURAL_MAX_DIST = 10.0
# Scores a row is compared on, and whether higher is better.
METRICS = {"psnr": True, "ssim": True, "lpips": False, "abs_diff": False, "delta_1_25": True}


@dataclass(frozen=True)
class Scale:
    """Everything about a run that is not the architecture.

    ``width_divisor`` shrinks the paper's layer widths (decoder E) at the small scales so a
    row like "E = 768" stays 3x its "E = 256" sibling. ``frames`` is the length of each
    procedural camera path; training windows (``min_span``..``max_span`` frames, None = the
    whole path) and the evaluation views (:func:`eval_samples`, ``eval_span``) are drawn
    from it. ``seeds``: every row is trained once per seed ``0..seeds-1``
    (model init and data order). ``workers``: how many (row, seed) trainings run at once,
    each in its own process pinned to one CPU core (1: one after another in this process,
    on every core). On small models a CPU core is used better by its own training than by
    XLA's threads inside one step (:func:`run_table`); a worker holds ~1.5 GB.
    """

    name: str
    base: C.ModelConfig
    size: int  # square images, H = W (pixels)
    num_inputs: int
    num_targets: int
    batch: int  # global batch (scenes per step)
    steps: int
    lr: float
    warmup: int
    perceptual_weight: float
    eval_scenes: int
    frames: int
    lpips: bool
    timing_repeats: int
    width_divisor: int = 1
    seeds: int = 1
    min_span: int | None = None
    max_span: int | None = None
    eval_span: int | None = None
    workers: int = 1
    rescale: bool = True  # Long-LRM's per-window scale normalisation (geometry.normalize_scene)

    def __str__(self) -> str:
        m = self.base
        return (f"{self.name}: {self.size}x{self.size}, {self.num_inputs} inputs + {self.num_targets} targets, "
                f"batch {self.batch}, {self.steps} steps (lr {self.lr}), {self.seeds} seed(s) per row, "
                f"{self.eval_scenes} held-out scenes, {self.workers} worker(s); "
                f"backbone D={m.backbone.dims} {m.backbone.pattern!r} x{m.backbone.num_layers}, outputs {m.outputs}"
                + ("" if self.rescale else "; poses not rescaled (world units)"))

    def width(self, paper_width: int) -> int:
        """A paper layer width at this scale."""
        return paper_width // self.width_divisor


def smoke_base() -> C.ModelConfig:
    """:func:`~llrmpp_jax.config.tiny` with a Gaussian head for procedural rooms, which
    span a few units: Gaussians start at ``exp(-3)`` ~ 0.05 units rather than
    ``exp(-6.9)`` (visible at 32x32 from the start); :func:`make_scale` sets their distance
    range (:data:`PROCEDURAL_MAX_DIST`)."""
    base = C.tiny()
    return C.replace(base, head=C.replace(base.head, scale_bias=-3.0))


def cpu_base() -> C.ModelConfig:
    """The demo model (the ``demo`` recipe), whose recipe was measured on this kind of
    machine (``experiments/README.md``), with the paper's chosen rows: K = 16 Gaussians of
    F = 32 features per token (Table 4) and an ``LLGGG`` decoder of width 256 / 4 with S = 2
    partitions (Tables 5, 6). At 64x64 the K = 16 head gives one Gaussian per half-resolution
    canvas pixel (2x2 image pixels) per input view, the paper's density at 256x256. Each row
    then sets its own K, F, decoder, S.

    The splat buffer holds 16 intersections per Gaussian, every tile of a 64x64 canvas, so
    it cannot overflow at this scale: with the default 8, the colour-Gaussian rows (one
    Gaussian per pixel, grown towards Long-LRM's largest scale within 400 steps) dropped
    ~5,000 intersections per training step (an interrupted Table 5 run, commit d07505d).

    The compositor advances 2 tiles per loop (``tiles_per_group``, default 64): a 64x64
    canvas has only 16 tiles, whose lists differ ~4x in length, and one loop over all of
    them runs as long as the longest. Measured on one core, one splat forward + backward of
    the Table 4 canvas-1.0 row (2 scenes x 2 targets x S = 2): 2.19 s with groups of 64,
    1.45 s with 4, 0.97 s with 2; the 32x32 canvas of the other rows gains ~10%. Outputs
    do not depend on it."""
    base = load_experiment("demo").model
    # The tables were run with the demo's earlier head start (every Gaussian at its patch
    # centre, scale_bias -2.5); the demo's grid start needs a square K, and Table 4 has K = 8, 32.
    head = C.replace(base.head, gaussians_per_token=16, feature_dim=32, anchors="centre", scale_bias=-2.5)
    return C.replace(base, head=head,
                     decoder=C.replace(base.decoder, blocks="LLGGG", dim=64, partitions=2),
                     splat=C.replace(base.splat, intersections_per_gaussian=16.0, tiles_per_group=2))


def _env_int(name: str, minimum: int) -> int | None:
    text = os.environ.get(name)
    if not text:
        return None
    try:
        value = int(text)
    except ValueError:
        raise ValueError(f"{name}={text!r}: expected an integer >= {minimum}") from None
    if value < minimum:
        raise ValueError(f"{name}={text!r}: expected an integer >= {minimum}, got {value}")
    return value


def scale_name() -> str:
    """``LLRMPP_NOTEBOOK_SCALE`` (default ``"smoke"``), checked."""
    name = os.environ.get("LLRMPP_NOTEBOOK_SCALE", "smoke")
    if name not in SCALES:
        raise ValueError(f"LLRMPP_NOTEBOOK_SCALE={name!r}: expected one of {', '.join(SCALES)}")
    return name


def make_scale(name: str, *, paper_views: int, depth: bool = False, paper_steps: int = 10_000,
               cpu_seeds: int = 3, cpu_steps: int = CPU_STEPS) -> Scale:
    """The ``"smoke"``, ``"cpu"`` or ``"paper"`` scale of a table whose paper setting has
    ``paper_views`` input views at 256x256 (``depth``: ScanNet-style colour + depth).
    ``cpu_seeds``: seeds per row at the cpu scale (3; a table whose rows are cheap enough
    runs more within the hour, for narrower intervals). ``cpu_steps``: training steps at
    the cpu scale (:data:`CPU_STEPS`; a table whose chosen row needs longer to clear the
    baselines, as depth does, sets its own)."""
    if cpu_seeds < 1:
        raise ValueError(f"make_scale: cpu_seeds must be >= 1, got {cpu_seeds}")
    if cpu_steps < 1:
        raise ValueError(f"make_scale: cpu_steps must be >= 1, got {cpu_steps}")
    if name == "smoke":
        scale = Scale(name="smoke", base=smoke_base(), size=32, num_inputs=2, num_targets=2, batch=2, steps=40,
                      lr=2e-3, warmup=10, perceptual_weight=0.0, eval_scenes=4, frames=16, lpips=False,
                      timing_repeats=3, width_divisor=4)
    elif name == "cpu":
        scale = Scale(name="cpu", base=cpu_base(), size=64, num_inputs=4, num_targets=2, batch=2, steps=cpu_steps,
                      lr=2e-3, warmup=50, perceptual_weight=0.0, eval_scenes=16, frames=16, lpips=True,
                      timing_repeats=3, width_divisor=4, seeds=cpu_seeds, min_span=6, max_span=10, eval_span=8,
                      workers=min(CPU_WORKERS, len(os.sched_getaffinity(0))))
    elif name == "paper":
        base = C.paper_scannet() if depth else C.paper_dl3dv()
        scale = Scale(name="paper", base=base, size=256, num_inputs=paper_views, num_targets=8, batch=8,
                      steps=paper_steps, lr=4e-4, warmup=min(2000, paper_steps // 10), perceptual_weight=0.5,
                      eval_scenes=64, frames=max(64, 2 * paper_views + 16), lpips=True, timing_repeats=10,
                      seeds=3)
    else:
        raise ValueError(f"make_scale: name must be one of {', '.join(SCALES)}, got {name!r}")
    if name != "paper":  # the paper scale keeps its data's normalisation, range and depth_bias
        base = C.replace(scale.base, head=C.replace(scale.base.head, max_dist=PROCEDURAL_MAX_DIST))
        if depth:
            base = C.replace(base, decoder=C.replace(base.decoder, depth_bias=PROCEDURAL_DEPTH_BIAS))
        scale = dataclasses.replace(scale, base=base, rescale=False)
    if depth:
        scale = dataclasses.replace(scale, base=C.replace(scale.base, outputs=("rgb", "depth")))
    steps = _env_int("LLRMPP_NOTEBOOK_STEPS", 0)
    if steps is not None:
        scale = dataclasses.replace(scale, steps=steps, warmup=min(scale.warmup, steps))
    seeds = _env_int("LLRMPP_NOTEBOOK_SEEDS", 1)
    if seeds is not None:
        scale = dataclasses.replace(scale, seeds=seeds)
    workers = _env_int("LLRMPP_NOTEBOOK_WORKERS", 1)
    if workers is not None:
        scale = dataclasses.replace(scale, workers=workers)
    return scale


@dataclass(frozen=True)
class Variant:
    """One row of an ablation table.

    ``labels``: the row's label columns as the paper prints them. ``build``: base config ->
    the row's config (``None``: the row cannot be reproduced here; ``note`` says why).
    ``paper``: the paper's reported numbers for the row (strings as printed, "-" = none).
    ``grad_weight`` / ``normal_weight``: the depth loss's auxiliary weights (Table 7).
    """

    labels: dict[str, str]
    build: Callable[[C.ModelConfig], C.ModelConfig] | None
    paper: dict[str, str]
    chosen: bool = False
    grad_weight: float = 0.1
    normal_weight: float = 0.1
    note: str = ""


@dataclass(frozen=True)
class Ordering:
    """A claim of the paper: row ``better`` beats row ``worse`` on ``metric`` (a key of
    :data:`METRICS`; "beats" = higher, or lower for LPIPS and Abs Diff). ``text`` names it."""

    text: str
    better: int
    worse: int
    metric: str = "psnr"

    def __post_init__(self) -> None:
        if self.metric not in METRICS:
            raise ValueError(f"Ordering {self.text!r}: metric must be one of {sorted(METRICS)}, got {self.metric!r}")


def selected(variants: Sequence[Variant]) -> list[tuple[int, Variant]]:
    """``(index, variant)`` of the rows to run: all, or those in ``LLRMPP_NOTEBOOK_ROWS``."""
    rows = os.environ.get("LLRMPP_NOTEBOOK_ROWS")
    if not rows:
        return list(enumerate(variants))
    if rows == "none":
        return []
    try:
        keep = [int(r) for r in rows.split(",")]
    except ValueError:
        raise ValueError(f"LLRMPP_NOTEBOOK_ROWS={rows!r}: expected comma-separated row indices or 'none'") from None
    bad = [r for r in keep if not 0 <= r < len(variants)]
    if bad:
        raise ValueError(f"LLRMPP_NOTEBOOK_ROWS={rows!r}: rows {bad} outside 0..{len(variants) - 1}")
    return [(i, variants[i]) for i in keep]


# ----------------------------------------------------------------------------- training


def row_objective(cfg: C.ModelConfig, scale: Scale, grad_weight: float, normal_weight: float, vgg: Any):
    """The training objective (:func:`llrmpp_jax.objective.objective`) of a row: colour loss
    with the scale's perceptual weight, plus the depth loss with the row's auxiliary weights
    when the model renders depth."""
    weights = LossWeights(perceptual=scale.perceptual_weight, depth_grad=grad_weight, depth_normal=normal_weight)
    return make_objective(cfg, weights, vgg)


def _device_count(batch: int) -> int:
    """Most local devices that split ``batch`` evenly."""
    return max(d for d in range(1, jax.local_device_count() + 1) if batch % d == 0)


def init_model(cfg: C.ModelConfig, scale: Scale, seed: int = 0) -> dict:
    """Fresh float32 parameters of ``cfg`` from ``seed``."""
    params = init_params(jax.random.key(seed), cfg, scale.num_inputs, scale.size, scale.size, scale.num_targets)
    # Parameters are float32 by contract (train state); cast leaves that x64 made float64.
    return jax.tree.map(lambda x: x if x.dtype == jnp.float32 else x.astype(jnp.float32), params)


@functools.lru_cache(maxsize=None)
def _train_fns(cfg: C.ModelConfig, scale: Scale, grad_weight: float, normal_weight: float):
    """``(optimizer, pmapped step)`` of a row, built once so its seeds share one compilation."""
    vgg = load_vgg16_lpips() if scale.perceptual_weight else None
    opt_cfg = T.OptimizerConfig(lr=scale.lr, warmup_steps=scale.warmup, total_steps=max(scale.steps, 1),
                                no_decay_names=("global_tokens",))
    optimizer = T.make_optimizer(opt_cfg)
    step = T.pmap_train_step(T.make_train_step(
        row_objective(cfg, scale, grad_weight, normal_weight, vgg),
        optimizer, T.make_schedule(opt_cfg)), donate=True)
    init = jax.jit(lambda p, k: T.init_train_state(p, optimizer, k))
    return init, step


@dataclass
class Trained:
    """A trained row: ``params``, per-step ``losses`` [steps], wall-clock ``seconds``
    (compile included), ``dropped`` = splat intersections lost to capacity, summed, and
    ``snapshots``: the params after each step asked for in :func:`train`."""

    params: dict
    losses: np.ndarray
    seconds: float
    dropped: int
    snapshots: dict[int, dict] = dataclasses.field(default_factory=dict)


def train(cfg: C.ModelConfig, scale: Scale, variant: Variant, seed: int = 0, snapshots: Sequence[int] = ()
          ) -> Trained:
    """Train ``cfg`` for ``scale.steps`` steps on procedural scenes, data-parallel over the
    local devices (pmap step of :mod:`llrmpp_jax.train`). ``seed`` sets the init and the
    data order; every row sees the same batches for the same seed (paired comparisons).
    ``snapshots``: steps after which to keep a copy of the params (the pilot's budgets)."""
    t0 = time.perf_counter()
    depth = "depth" in cfg.outputs
    init, step = _train_fns(cfg, dataclasses.replace(scale, seeds=1), variant.grad_weight, variant.normal_weight)
    n_dev = _device_count(scale.batch)
    # One jitted init: optimizer.init run eagerly would compile a fill op per leaf shape.
    state = T.replicate_for_pmap(init(init_model(cfg, scale, seed), jax.random.key(seed)), n_dev)
    source = ProceduralSource(ProceduralConfig(height=scale.size, width=scale.size, num_frames=scale.frames),
                              size=TRAIN_SCENES)
    batch_cfg = BatchConfig(global_batch=scale.batch, num_inputs=scale.num_inputs, num_targets=scale.num_targets,
                            with_depth=depth, min_span=scale.min_span, max_span=scale.max_span, rescale=scale.rescale)
    losses, dropped, kept = [], [], {}
    host_params = lambda state: jax.tree.map(lambda x: x[0], jax.device_get(state.params))  # noqa: E731 (device 0's)

    def record(info: StepInfo) -> None:  # the loss curve, lost splat intersections, the snapshots asked for
        metrics = jax.device_get(info.metrics)  # host copies: indexing device arrays compiles ops
        losses.append(float(metrics["loss"][0]))
        dropped.append(float(metrics["splat_dropped"][0]) * n_dev)
        if info.step in snapshots:
            kept[info.step] = host_params(info.state)

    with BatchIterator(source, batch_cfg, seed=seed, num_devices=n_dev) as batches:
        done = run_stage(state, step, (T.shard_for_pmap(b, n_dev) for b in batches), steps=scale.steps,
                         hooks=[record])
    return Trained(host_params(done.state), np.asarray(losses, np.float32), time.perf_counter() - t0,
                   int(sum(dropped)), kept)


# --------------------------------------------------------------------------- evaluation


def eval_samples(scale: Scale, depth: bool) -> list[dict[str, np.ndarray]]:
    """Held-out procedural scenes (seeds ``EVAL_SEED + i``). With ``scale.eval_span`` None,
    each is split as the paper evaluates (every 8th frame a target, k-means inputs over the
    rest); otherwise, as :func:`llrmpp_jax.data.held_out.eval_samples` does for procedural data,
    the training view sampler draws the views from a window of ``eval_span`` frames with a
    fixed seed per scene (on short paths, every-8th targets are far from every input). One
    sample per scene, with a leading batch axis of 1."""
    cfg = ProceduralConfig(height=scale.size, width=scale.size, num_frames=scale.frames)
    geom = ViewGeometry()
    samples = []
    for i in range(scale.eval_scenes):
        scene = procedural_scene(EVAL_SEED + i, cfg)
        if scale.eval_span is None:
            inputs, targets = eval_views(scene.c2w, scale.num_inputs)
        else:
            inputs, targets = training_views(np.random.default_rng([7, i]), len(scene.c2w), scale.num_inputs,
                                             scale.num_targets, scale.eval_span, scale.eval_span, input_weight=0.0)
        s = make_sample(scene, inputs, targets, geom, with_depth=depth, rescale=scale.rescale)
        samples.append({k: v[None] for k, v in s.items()})
    return samples


def _score(pred: jax.Array, s: dict, lpips_params: Any, depth: jax.Array | None) -> dict:
    """Per-target scores of ``pred`` [1, T, H, W, 3] (and ``depth`` [1, T, H, W]) against sample ``s``."""
    pred, gt = jnp.clip(pred[0], 0.0, 1.0), s["target_images"][0]  # [T, H, W, 3]
    scores = {"psnr": psnr(pred, gt), "ssim": ssim(pred, gt)}
    if lpips_params is not None:
        scores["lpips"] = lpips(lpips_params, pred, gt)
    if depth is not None:  # Abs Diff in the scene's own units, as llrmpp evaluate reports it
        world = 1.0 / s["scene_scale"][0]
        dm = depth_metrics(depth[0] * world, s["target_depth"][0] * world)
        scores.update(abs_diff=dm["abs_diff"], delta_1_25=dm["delta_1_25"])
    return scores


_jitted_score = jax.jit(_score)


@functools.lru_cache(maxsize=None)
def _jitted(cfg: C.ModelConfig, size: int):
    """Jitted ``reconstruct`` and ``render`` for ``cfg``, one pair per ``(cfg, size)`` so
    evaluation and timing share their compilations."""
    recon = jax.jit(lambda p, s: reconstruct(p, cfg, s["input_images"], s["input_c2w"], s["input_intrinsics"]))
    rend = jax.jit(lambda p, g, c2w, k: render(p, cfg, g, c2w, k, size, size, cfg.outputs))
    return recon, rend


def _mean_scores(per_sample: Sequence[dict]) -> dict[str, float]:
    keys = per_sample[0].keys()
    return {k: float(np.nanmean(np.concatenate([np.atleast_1d(d[k]) for d in per_sample]))) for k in keys}


def evaluate(params: dict, cfg: C.ModelConfig, scale: Scale, samples: Sequence[dict],
             lpips_params: Any = None) -> dict[str, float]:
    """Mean PSNR / SSIM (/ LPIPS with ``lpips_params``) over every target of ``samples``,
    plus depth Abs Diff and delta < 1.25 when ``cfg`` renders depth, and ``eval_dropped``
    (splat intersections lost to capacity, summed)."""
    recon, rend = _jitted(cfg, scale.size)
    scores, dropped = [], 0
    for s in samples:
        out = rend(params, recon(params, s), s["target_c2w"], s["target_intrinsics"])
        depth = out.images["depth"][..., 0] if "depth" in cfg.outputs else None
        scores.append(jax.device_get(_jitted_score(out.images["rgb"], s, lpips_params, depth)))
        dropped += int(np.sum(out.dropped))
    return {**_mean_scores(scores), "eval_dropped": dropped}


def _median_seconds(fn: Callable[[], Any], repeats: int) -> float:
    jax.block_until_ready(fn())  # compile + warm up
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        jax.block_until_ready(fn())
        times.append(time.perf_counter() - t0)
    return float(np.median(times))


def time_model(params: dict, cfg: C.ModelConfig, scale: Scale, sample: dict) -> dict[str, float]:
    """Median wall-clock seconds of ``reconstruct`` (one scene) and of ``render`` per target
    frame (all outputs, splat + decode), after compilation; ``gaussians`` per scene."""
    recon, rend = _jitted(cfg, scale.size)
    g = recon(params, sample)
    n_targets = sample["target_c2w"].shape[1]
    return {
        "gaussians": int(g.means.shape[1]),
        "recon_s": _median_seconds(lambda: recon(params, sample), scale.timing_repeats),
        "render_s": _median_seconds(lambda: rend(params, g, sample["target_c2w"], sample["target_intrinsics"]),
                                    scale.timing_repeats) / n_targets,
    }


# --------------------------------------------------------------------------- statistics


def interval(values: Sequence[float], confidence: float = 0.95) -> dict[str, float]:
    """Mean, sample standard deviation and the half-width of the two-sided Student-t
    ``confidence`` interval of the mean (NaN for fewer than 2 values)."""
    x = np.asarray(values, np.float64)
    n = len(x)
    if n < 2:
        return {"mean": float(np.mean(x)) if n else float("nan"), "std": float("nan"), "ci": float("nan")}
    sd = float(np.std(x, ddof=1))
    return {"mean": float(np.mean(x)), "std": sd,
            "ci": float(stats.t.ppf(0.5 + confidence / 2, n - 1) * sd / np.sqrt(n))}


def _summarise(per_seed: Sequence[dict[str, float]]) -> dict[str, Any]:
    """Per-metric mean (under the metric's own key, so tables read as before), ``_std``,
    ``_ci`` and the per-seed ``_seeds`` list."""
    out: dict[str, Any] = {}
    for k in per_seed[0]:
        values = [d[k] for d in per_seed]
        iv = interval(values)
        out.update({k: iv["mean"], f"{k}_std": iv["std"], f"{k}_ci": iv["ci"], f"{k}_seeds": values})
    return out


def compare(results: Sequence[dict[str, Any]], orderings: Sequence[Ordering]) -> list[dict[str, Any]]:
    """For each ordering, the paired per-seed difference ``better - worse`` (sign flipped for
    lower-is-better metrics, so > 0 means the paper's ordering holds) with its 95% interval,
    and a verdict: ``reproduced`` (interval above 0), ``reversed`` (below 0), ``not resolved``
    (contains 0, or fewer than 2 seeds), ``not run`` (a row did not run)."""
    by_row = {r["row"]: r for r in results}
    out = []
    for o in orderings:
        a, b = by_row.get(o.better), by_row.get(o.worse)
        entry: dict[str, Any] = {"ordering": o.text, "better": o.better, "worse": o.worse, "metric": o.metric}
        if a is None or b is None or a["status"] != "ok" or b["status"] != "ok" or o.metric not in a:
            out.append({**entry, "verdict": "not run"})
            continue
        sign = 1.0 if METRICS[o.metric] else -1.0
        diffs = sign * (np.asarray(a[f"{o.metric}_seeds"]) - np.asarray(b[f"{o.metric}_seeds"]))
        iv = interval(diffs)
        paper = _paper_number(a, o.metric), _paper_number(b, o.metric)
        if len(diffs) < 2 or not abs(iv["mean"]) > iv["ci"]:
            verdict = "not resolved"
        else:
            verdict = "reproduced" if iv["mean"] > 0 else "reversed"
        out.append({**entry, "diff": iv["mean"], "diff_ci": iv["ci"], "diff_seeds": diffs.tolist(),
                    "paper_diff": None if None in paper else sign * (paper[0] - paper[1]), "verdict": verdict})
    return out


_PAPER_KEY = {"psnr": "PSNR", "ssim": "SSIM", "lpips": "LPIPS", "abs_diff": "Abs Diff", "delta_1_25": "delta<1.25"}


def _paper_number(row: dict[str, Any], metric: str) -> float | None:
    try:
        return float(row["paper"].get(_PAPER_KEY[metric], "-"))
    except ValueError:
        return None


# ------------------------------------------------------------------------------- tables


def references(cfg: C.ModelConfig, scale: Scale, samples: Sequence[dict], lpips_params: Any = None
               ) -> list[dict[str, Any]]:
    """What a row must beat, on the held-out ``samples``: ``cfg`` untrained (one init per
    seed) and the two baselines of :func:`llrmpp_jax.evaluate.baseline_predictions`
    (mean input colour; the input view nearest each target, shown as-is)."""
    untrained = [evaluate(init_model(cfg, scale, seed), cfg, scale, samples, lpips_params)
                 for seed in range(scale.seeds)]
    rows = [{"name": "untrained", **_summarise(untrained)}]
    for method in ("mean_colour", "nearest_view"):
        scores = []
        for s in samples:
            pred = baseline_predictions({k: v[0] for k, v in s.items()})[method]
            scores.append(jax.device_get(_jitted_score(jnp.asarray(pred)[None], s, lpips_params, None)))
        rows.append({"name": method.replace("_", " "), **_mean_scores(scores)})
    return rows


@dataclass
class TableRun:
    """Everything a notebook shows: the ``results`` of each selected row, the
    ``references`` (untrained chosen row, baselines), per-row mean training ``curves``
    (loss per step, averaged over seeds) and the wall ``seconds`` of the whole table."""

    scale: Scale
    results: list[dict[str, Any]]
    references: list[dict[str, Any]]
    curves: dict[int, list[float]]
    seconds: float


@functools.lru_cache(maxsize=None)
def _held_out(scale: Scale, depth: bool) -> tuple[dict[str, np.ndarray], ...]:
    """:func:`eval_samples`, made once per process."""
    return tuple(eval_samples(scale, depth))


@functools.lru_cache(maxsize=None)
def _lpips_params(scale: Scale) -> Any:
    """The LPIPS weights when ``scale.lpips``, else None; loaded once per process."""
    return load_lpips_params() if scale.lpips else None


@dataclass
class SeedRun:
    """One row trained at one seed and scored on the held-out scenes: the
    :func:`evaluate` ``scores``, the :class:`Trained` ``losses``, ``seconds`` and
    ``dropped``, and its ``params`` when asked for (the row's timings use seed 0's)."""

    scores: dict[str, float]
    losses: np.ndarray
    seconds: float
    dropped: int
    params: dict | None


def run_seed(cfg: C.ModelConfig, scale: Scale, variant: Variant, seed: int, keep_params: bool = False) -> SeedRun:
    """:func:`train` ``cfg`` at ``seed`` and :func:`evaluate` it on the held-out scenes."""
    trained = train(cfg, scale, variant, seed)
    scores = evaluate(trained.params, cfg, scale, _held_out(scale, "depth" in cfg.outputs), _lpips_params(scale))
    return SeedRun(scores, trained.losses, trained.seconds, trained.dropped, trained.params if keep_params else None)


def _pin_to_core(cores: Any) -> None:
    """Pool initializer: bind this worker to one core before JAX sizes its thread pool."""
    os.sched_setaffinity(0, {cores.get()})


@contextlib.contextmanager
def _main_hidden() -> Iterator[None]:
    """Hide ``__main__`` while pool workers start: multiprocessing's spawn re-runs the main
    script in every worker, which for a table run as ``python notebooks/table*.py`` would be
    the whole table again. Workers need only this module (in a notebook kernel, ``__main__``
    is no script and nothing changes)."""
    main = sys.modules["__main__"]
    sys.modules["__main__"] = types.ModuleType("__main__")
    try:
        yield
    finally:
        sys.modules["__main__"] = main


def _progress(text: str) -> None:
    """Print ``text`` in the notebook, and, when ``notebooks/_execute.py`` runs it
    (``LLRMPP_NOTEBOOK_ECHO``), on the kernel's own stderr: the terminal of
    ``make notebooks``, which shows cell outputs only at the end."""
    print(text, flush=True)
    if os.environ.get("LLRMPP_NOTEBOOK_ECHO") and sys.__stderr__ is not None and sys.stderr is not sys.__stderr__:
        print(text, file=sys.__stderr__, flush=True)


def _run_seeds(jobs: Sequence[tuple[int, C.ModelConfig, Variant, int]], scale: Scale
               ) -> Iterator[tuple[int, int, SeedRun]]:
    """Run each ``(row, cfg, variant, seed)`` job with :func:`run_seed`, yielding
    ``(row, seed, SeedRun)`` as they finish: in this process when ``scale.workers`` is 1,
    else on a pool of ``scale.workers`` spawned processes, each pinned to its own core (by
    ``os.sched_setaffinity``, the worker ``i`` on the ``i``-th core this process may use).
    Seed 0's params come back for the row's timings."""
    if scale.workers == 1:
        for row, cfg, variant, seed in jobs:
            yield row, seed, run_seed(cfg, scale, variant, seed, keep_params=seed == 0)
        return
    ctx = multiprocessing.get_context("spawn")  # fork after JAX has started threads is unsafe
    cores = ctx.Queue()
    allowed = sorted(os.sched_getaffinity(0))
    for i in range(scale.workers):
        cores.put(allowed[i % len(allowed)])
    with ProcessPoolExecutor(scale.workers, mp_context=ctx, initializer=_pin_to_core, initargs=(cores,)) as pool:
        # A Variant's build function may be a notebook lambda (not picklable); workers need
        # only its loss weights.
        with _main_hidden():  # workers start on submit (spawn context)
            futures = {pool.submit(run_seed, cfg, scale, dataclasses.replace(variant, build=None), seed, seed == 0):
                       (row, seed) for row, cfg, variant, seed in jobs}
        for future in as_completed(futures):
            row, seed = futures[future]
            yield row, seed, future.result()


def run_table(variants: Sequence[Variant], scale: Scale) -> TableRun:
    """Train (once per seed), evaluate and time each selected row (:func:`selected`); rows
    without a config are kept with ``status`` saying why. One result dict per row: its
    labels, ``paper`` numbers, ``status``, and for run rows ``params``, ``decoder_params``,
    ``decoder_dim`` (None in colour mode), ``train_s`` (per seed, mean), ``final_loss``,
    ``train_dropped``, the :func:`evaluate` scores summarised over seeds by
    :func:`_summarise` and the :func:`time_model` timings (seed 0's params, timed in this
    process after every training has finished, so no worker competes with them).

    The trainings of all rows and seeds run ``scale.workers`` at a time
    (:func:`_run_seeds`); ``train_s`` is then the time of a training that shared the
    machine with the other workers, each on one core."""
    t_start = time.perf_counter()
    rows = selected(variants)
    configs = {index: v.build(scale.base) for index, v in rows if v.build is not None}
    jobs = [(index, configs[index], v, seed) for index, v in rows if index in configs for seed in range(scale.seeds)]
    runs: dict[int, dict[int, SeedRun]] = {index: {} for index in configs}
    for index, seed, r in _run_seeds(jobs, scale):
        runs[index][seed] = r
        _progress(f"row {index} {variants[index].labels} seed {seed}: PSNR {r.scores['psnr']:.2f}, "
                  f"trained in {r.seconds:.0f} s ({sum(map(len, runs.values()))}/{len(jobs)} done, "
                  f"{(time.perf_counter() - t_start) / 60:.1f} min)")
    results, curves = [], {}
    for index, v in rows:
        row: dict[str, Any] = {"row": index, **v.labels, "chosen": v.chosen, "paper": dict(v.paper)}
        if index not in configs:
            results.append({**row, "status": f"not run: {v.note}"})
            continue
        cfg, per_seed = configs[index], [runs[index][seed] for seed in range(scale.seeds)]
        samples = _held_out(scale, "depth" in cfg.outputs)
        row.update(time_model(per_seed[0].params, cfg, scale, samples[0]),
                   params=count_params(per_seed[0].params),
                   decoder_params=count_params(per_seed[0].params.get("decoder", {})),
                   decoder_dim=cfg.decoder.dim if cfg.head.mode == "feature" else None)
        tails = [r.losses[-max(1, len(r.losses) // 10):] for r in per_seed]
        row.update(status="ok", seeds=scale.seeds, **_summarise([
            {**r.scores, "train_s": r.seconds, "train_dropped": float(r.dropped),
             "final_loss": float(np.mean(tail)) if len(tail) else float("nan")} for r, tail in zip(per_seed, tails)]))
        curves[index] = np.mean([r.losses for r in per_seed], axis=0).tolist()
        results.append(row)
    runnable = [v for index, v in rows if index in configs]
    chosen = [v for v in runnable if v.chosen] or runnable
    refs = []
    if chosen:
        cfg = chosen[0].build(scale.base)
        refs = references(cfg, scale, _held_out(scale, "depth" in cfg.outputs), _lpips_params(scale))
    return TableRun(scale, results, refs, curves, time.perf_counter() - t_start)


def _fmt(x: Any, digits: int) -> str:
    if x is None:
        return "-"
    if isinstance(x, str):
        return x
    if isinstance(x, (int, np.integer)):
        return f"{int(x):,}"
    return f"{x:.{digits}f}" if np.isfinite(x) else "nan"


@dataclass(frozen=True)
class Column:
    """A column of :func:`format_table`: ``key`` in a result (``"paper:NAME"`` reads the
    paper's number), its ``title``, decimal ``digits`` and a ``scale`` factor (e.g. 1000
    for ms). A key with a ``_ci`` companion is printed as ``mean ± half-width``."""

    key: str
    title: str
    digits: int = 2
    scale: float = 1.0


def _cell(r: dict[str, Any], c: Column) -> str:
    if c.key.startswith("paper:"):
        return r["paper"].get(c.key[6:], "-")
    if r.get("status", "ok") != "ok":
        return "-"
    value = r.get(c.key)
    if isinstance(value, float):
        value = value * c.scale
    text = _fmt(value, c.digits)
    ci = r.get(f"{c.key}_ci")
    if isinstance(ci, float) and np.isfinite(ci):
        text += f" ± {_fmt(ci * c.scale, c.digits)}"
    return text


def format_table(run: TableRun, label_keys: Sequence[str], columns: Sequence[Column] = ()) -> str:
    """A Markdown table: one line per result, the label columns, then ``columns``; ``*``
    marks the paper's chosen row; then the references (untrained, baselines); rows that did
    not run show their status, rows whose splat buffer overflowed say by how much; a last
    line gives the scale, seeds, wall time and commit.
    ``±``: half-width of the 95% interval over seeds."""
    head = ["", *label_keys, *[c.title for c in columns]]
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for r in run.results:
        cells = ["*" if r["chosen"] else "", *[str(r[k]) for k in label_keys]]
        lines.append("| " + " | ".join(cells + [_cell(r, c) for c in columns]) + " |")
    for ref in run.references:
        cells = ["", ref["name"], *[""] * (len(label_keys) - 1)]
        own = [c for c in columns if not c.key.startswith("paper:")]
        lines.append("| " + " | ".join(cells + [_cell({"paper": {}, **ref}, c) if c in own and c.key in ref
                                                else "" for c in columns]) + " |")
    notes = [f"row {r['row']}: {r['status']}" for r in run.results if r["status"] != "ok"]
    # Splat capacity overflow (SplatConfig.max_intersections) loses Gaussians: say so by row.
    notes += [f"row {r['row']}: the splat buffer overflowed: {r['train_dropped'] / max(run.scale.steps, 1):,.0f} "
              f"intersections dropped per training step, {r['eval_dropped'] / run.scale.eval_scenes:,.0f} "
              "per held-out scene (mean over seeds)"
              for r in run.results if r["status"] == "ok" and (r["train_dropped"] > 0 or r["eval_dropped"] > 0)]
    footer = (f"{run.scale.name} scale, {run.scale.seeds} seed(s) per row, {run.scale.steps} steps, "
              f"wall time {run.seconds / 60:.1f} min, commit {commit()}")
    return "\n".join(lines + [""] + notes + ([""] if notes else []) + [footer])


def ordering_cells(c: dict[str, Any]) -> tuple[str, str]:
    """The paper's difference and ours (mean paired difference over seeds ± 95% half-width)
    of one :func:`compare` entry, as printed ("-" where there is none)."""
    ours = (f"{c['diff']:+.3f} ± {c['diff_ci']:.3f}" if "diff" in c and np.isfinite(c["diff_ci"])
            else f"{c['diff']:+.3f}" if "diff" in c else "-")
    paper = f"{c['paper_diff']:+.3f}" if c.get("paper_diff") is not None else "-"
    return paper, ours


def format_orderings(comparisons: Sequence[dict[str, Any]]) -> str:
    """A Markdown table of :func:`compare`'s verdicts: the paper's difference, ours
    (:func:`ordering_cells`; > 0 = the paper's ordering holds)."""
    lines = ["| paper ordering | metric | paper diff | our diff (95% interval) | verdict |", "|---|---|---|---|---|"]
    for c in comparisons:
        paper, ours = ordering_cells(c)
        lines.append(f"| {c['ordering']} | {c['metric']} | {paper} | {ours} | {c['verdict']} |")
    return "\n".join(lines)


def _row_name(r: dict[str, Any], label_keys: Sequence[str]) -> str:
    return " ".join(str(r[k]) for k in label_keys)


def plot(run: TableRun, label_keys: Sequence[str], metric: str = "psnr", title: str = ""):
    """A matplotlib figure: left, ``metric`` per row (mean and 95% interval over seeds, each
    seed a dot, the references as horizontal lines); right, each row's training loss (mean
    over seeds, 25-step moving average)."""
    import matplotlib.pyplot as plt

    fig, (ax, ax_loss) = plt.subplots(1, 2, figsize=(12, 4.2))
    ok = [r for r in run.results if r["status"] == "ok"]
    names = [_row_name(r, label_keys) + (" *" if r["chosen"] else "") for r in ok]
    for i, r in enumerate(ok):
        ci = r.get(f"{metric}_ci", float("nan"))
        ax.errorbar(i, r[metric], yerr=ci if np.isfinite(ci) else None, fmt="o", color="C0", capsize=4)
        ax.plot([i] * len(r[f"{metric}_seeds"]), r[f"{metric}_seeds"], ".", color="C0", alpha=0.4)
    for j, ref in enumerate(run.references):
        if metric in ref:
            ax.axhline(ref[metric], color=f"C{j + 1}", ls="--", lw=1, label=ref["name"])
    ax.set_xticks(range(len(ok)), names, rotation=30, ha="right")
    ax.set_ylabel(f"held-out {metric} (mean, 95% interval)")
    if ax.get_legend_handles_labels()[0]:
        ax.legend(fontsize=8)
    ax.set_title(title or "rows")
    window = 25
    for i, r in enumerate(ok):
        loss = np.asarray(run.curves[r["row"]])
        if len(loss) >= window:
            loss = np.convolve(loss, np.ones(window) / window, mode="valid")
        ax_loss.plot(np.arange(len(loss)) + 1, loss, label=names[i], color=f"C{i}")
    ax_loss.set_yscale("log")
    ax_loss.set_xlabel("step")
    ax_loss.set_ylabel("training loss (mean over seeds)")
    if ok:
        ax_loss.legend(fontsize=7)
    fig.tight_layout()
    return fig


def commit() -> str:
    """The repository's short commit, with ``+dirty`` when tracked files differ from it."""
    def git(*args: str) -> str:
        return subprocess.run(["git", *args], cwd=ROOT, capture_output=True, text=True).stdout.strip()
    head = git("rev-parse", "--short", "HEAD") or "unknown"
    return head + ("+dirty" if git("status", "--porcelain", "--untracked-files=no") else "")


def machine() -> str:
    """One line: CPU / accelerator, core count, JAX backend and version."""
    dev = jax.devices()[0]
    return (f"{platform.processor() or platform.machine()}, {os.cpu_count()} cores, "
            f"jax {jax.__version__} on {dev.platform} ({dev.device_kind})")


def save(name: str, run: TableRun, comparisons: Sequence[dict[str, Any]], figure: Any = None) -> str:
    """Write ``{name}_{scale}.json`` (and ``.png`` for ``figure``) under
    ``LLRMPP_NOTEBOOK_OUT`` (default ``experiments/results/ablations``), print and return the
    JSON path."""
    out = os.environ.get("LLRMPP_NOTEBOOK_OUT") or os.path.join(ROOT, "experiments", "results", "ablations")
    os.makedirs(out, exist_ok=True)
    path = os.path.join(out, f"{name}_{run.scale.name}.json")
    record = {
        "table": name, "scale": str(run.scale), "scale_name": run.scale.name, "seeds": run.scale.seeds,
        "steps": run.scale.steps, "commit": commit(), "machine": machine(), "wall_s": run.seconds,
        "results": run.results, "references": run.references, "orderings": list(comparisons),
        "curves": {str(k): v for k, v in run.curves.items()},
    }
    with open(path, "w") as f:
        json.dump(record, f, indent=1, default=float)
    if figure is not None:
        figure.savefig(path[:-5] + ".png", dpi=100)
    print(f"saved {path}")
    return path
