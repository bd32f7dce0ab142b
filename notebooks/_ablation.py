"""Shared machinery of the ablation notebooks (paper Tables 4-7).

A notebook lists its table's rows as :class:`Variant` s (row labels, a function that
turns the scale's base :class:`~llrmpp_jax.config.ModelConfig` into the row's config,
and the paper's numbers), then calls :func:`run_table`: every runnable row is trained
briefly on procedural scenes with :func:`train`, scored on held-out procedural scenes
with :func:`evaluate` and timed with :func:`time_model`. :func:`format_table` prints the
rows next to the paper's numbers.

Two scales (:func:`make_scale`):

* ``"smoke"``: a tiny model (:func:`llrmpp_jax.config.tiny` with a Gaussian head sized for
  procedural rooms) at 32x32, 2 input views, 40 steps, MSE loss only, no LPIPS. The
  numbers only show that the pipeline runs; they are not comparable with the paper's.
  Compile-bound on a CPU: every row compiles its own init, train step and renderers, about
  a minute per row on 2 cores (2 minutes when the cores are shared), so a table takes
  several minutes. Setting ``JAX_COMPILATION_CACHE_DIR`` makes reruns about 2x faster.
* ``"paper"``: the paper's architecture (:func:`paper_dl3dv` / :func:`paper_scannet`) at
  256x256 with the table's view count, MSE + 0.5 perceptual loss, LPIPS; meant for
  accelerators. The data are still procedural scenes (swap ``source`` for a
  ``FileSource`` of DL3DV / ScanNet scenes to approach the paper's setting).

Environment overrides (for tests and quick looks): ``LLRMPP_NOTEBOOK_STEPS`` sets the
number of train steps, ``LLRMPP_NOTEBOOK_ROWS`` a comma-separated list of row indices to
run (the others are left out of the results; ``none`` runs no row).
"""

from __future__ import annotations

import dataclasses
import functools
import os
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

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
)
from llrmpp_jax.losses import depth_loss, rgb_loss
from llrmpp_jax.metrics import depth_metrics, load_lpips_params, lpips, psnr, ssim
from llrmpp_jax.model import init_params, reconstruct, render
from llrmpp_jax.nn.backbone import count_params
from llrmpp_jax.perceptual import load_vgg16_lpips
from llrmpp_jax import train as T

TRAIN_SCENES = 100_000  # training seeds are [0, TRAIN_SCENES)
EVAL_SEED = 1_000_000  # held-out seeds start here (disjoint from training)


@dataclass(frozen=True)
class Scale:
    """Everything about a run that is not the architecture.

    ``width_divisor`` shrinks the paper's layer widths (decoder E) in smoke mode so a row
    like "E = 768" stays 3x its "E = 256" sibling. ``frames`` is the length of each
    procedural camera path; training windows and the evaluation split (every 8th frame a
    target, k-means inputs over the rest) are drawn from it.
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
    seed: int = 0

    def __str__(self) -> str:
        m = self.base
        return (f"{self.name}: {self.size}x{self.size}, {self.num_inputs} inputs + {self.num_targets} targets, "
                f"batch {self.batch}, {self.steps} steps (lr {self.lr}), {self.eval_scenes} held-out scenes; "
                f"backbone D={m.backbone.dims} {m.backbone.pattern!r} x{m.backbone.num_layers}, outputs {m.outputs}")

    def width(self, paper_width: int) -> int:
        """A paper layer width at this scale."""
        return paper_width // self.width_divisor


def smoke_base() -> C.ModelConfig:
    """:func:`~llrmpp_jax.config.tiny` with a Gaussian head for procedural rooms.

    Normalised procedural scenes span a few units (input cameras in ``[-1, 1]^3``), so the
    distance range is 16 units rather than Long-LRM's 500, and Gaussians start at
    ``exp(-3)`` ~ 0.05 units rather than ``exp(-6.9)`` (visible at 32x32 from the start).
    """
    base = C.tiny()
    return C.replace(base, head=C.replace(base.head, max_dist=16.0, scale_bias=-3.0))


def make_scale(name: str, *, paper_views: int, depth: bool = False, paper_steps: int = 10_000) -> Scale:
    """The ``"smoke"`` or ``"paper"`` scale of a table whose paper setting has
    ``paper_views`` input views at 256x256 (``depth``: ScanNet-style colour + depth)."""
    steps_env = os.environ.get("LLRMPP_NOTEBOOK_STEPS")
    if name == "smoke":
        base = smoke_base()
        scale = Scale(name="smoke", base=base, size=32, num_inputs=2, num_targets=2, batch=2, steps=40,
                      lr=2e-3, warmup=10, perceptual_weight=0.0, eval_scenes=4, frames=16, lpips=False,
                      timing_repeats=3, width_divisor=4)
    elif name == "paper":
        base = C.paper_scannet() if depth else C.paper_dl3dv()
        scale = Scale(name="paper", base=base, size=256, num_inputs=paper_views, num_targets=8, batch=8,
                      steps=paper_steps, lr=4e-4, warmup=min(2000, paper_steps // 10), perceptual_weight=0.5,
                      eval_scenes=64, frames=max(64, 2 * paper_views + 16), lpips=True, timing_repeats=10)
    else:
        raise ValueError(f"make_scale: name must be 'smoke' or 'paper', got {name!r}")
    if depth:
        scale = dataclasses.replace(scale, base=C.replace(scale.base, outputs=("rgb", "depth")))
    if steps_env:
        scale = dataclasses.replace(scale, steps=int(steps_env), warmup=min(scale.warmup, int(steps_env)))
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


def selected(variants: Sequence[Variant]) -> list[tuple[int, Variant]]:
    """``(index, variant)`` of the rows to run: all, or those in ``LLRMPP_NOTEBOOK_ROWS``."""
    rows = os.environ.get("LLRMPP_NOTEBOOK_ROWS")
    if not rows:
        return list(enumerate(variants))
    if rows == "none":
        return []
    keep = [int(r) for r in rows.split(",")]
    bad = [r for r in keep if not 0 <= r < len(variants)]
    if bad:
        raise ValueError(f"LLRMPP_NOTEBOOK_ROWS={rows!r}: rows {bad} outside 0..{len(variants) - 1}")
    return [(i, variants[i]) for i in keep]


# ----------------------------------------------------------------------------- training


def _loss_fn(cfg: C.ModelConfig, size: int, perceptual_weight: float, grad_weight: float,
             normal_weight: float, vgg: Any):
    """``(params, batch, key) -> (loss, metrics)`` on one batch shard (the layout of
    :mod:`llrmpp_jax.data.batching`): colour loss, plus the depth loss when the model
    renders depth."""

    def loss_fn(params, batch, key):
        del key  # the loss is deterministic
        g = reconstruct(params, cfg, batch["input_images"], batch["input_c2w"], batch["input_intrinsics"])
        out = render(params, cfg, g, batch["target_c2w"], batch["target_intrinsics"], size, size, cfg.outputs)
        loss, aux = rgb_loss(out.images["rgb"], batch["target_images"], vgg, perceptual_weight=perceptual_weight)
        metrics = {"mse": aux["mse"], "dropped": jnp.sum(out.dropped).astype(jnp.float32)}
        if "depth" in cfg.outputs:
            d_loss, d_aux = depth_loss(out.images["depth"][..., 0], batch["target_depth"], batch["target_intrinsics"],
                                       grad_weight=grad_weight, normal_weight=normal_weight)
            loss = loss + d_loss
            metrics["depth_loss"] = d_aux["depth"]
        return loss, metrics

    return loss_fn


def _device_count(batch: int) -> int:
    """Most local devices that split ``batch`` evenly."""
    return max(d for d in range(1, jax.local_device_count() + 1) if batch % d == 0)


def init_model(cfg: C.ModelConfig, scale: Scale) -> dict:
    """Fresh float32 parameters of ``cfg`` (seeded by ``scale.seed``)."""
    params = init_params(jax.random.key(scale.seed), cfg, scale.num_inputs, scale.size, scale.size,
                         scale.num_targets)
    # Parameters are float32 by contract (train state); cast leaves that x64 made float64.
    return jax.tree.map(lambda x: x if x.dtype == jnp.float32 else x.astype(jnp.float32), params)


@dataclass
class Trained:
    """A trained row: ``params``, per-step ``losses`` [steps], wall-clock ``seconds``
    (compile included), ``dropped`` = splat intersections lost to capacity, summed."""

    params: dict
    losses: np.ndarray
    seconds: float
    dropped: int


def train(cfg: C.ModelConfig, scale: Scale, variant: Variant) -> Trained:
    """Train ``cfg`` for ``scale.steps`` steps on procedural scenes, data-parallel over the
    local devices (pmap step of :mod:`llrmpp_jax.train`); every row sees the same batches."""
    t0 = time.perf_counter()
    depth = "depth" in cfg.outputs
    vgg = load_vgg16_lpips() if scale.perceptual_weight else None
    opt_cfg = T.OptimizerConfig(lr=scale.lr, warmup_steps=scale.warmup, total_steps=max(scale.steps, 1),
                                no_decay_names=("global_tokens",))
    optimizer = T.make_optimizer(opt_cfg)
    step = T.pmap_train_step(T.make_train_step(
        _loss_fn(cfg, scale.size, scale.perceptual_weight, variant.grad_weight, variant.normal_weight, vgg),
        optimizer, T.make_schedule(opt_cfg)), donate=True)
    n_dev = _device_count(scale.batch)
    # One jitted init: optimizer.init run eagerly would compile a fill op per leaf shape.
    state = jax.jit(lambda p, k: T.init_train_state(p, optimizer, k))(init_model(cfg, scale),
                                                                       jax.random.key(scale.seed))
    state = T.replicate_for_pmap(state, n_dev)
    source = ProceduralSource(ProceduralConfig(height=scale.size, width=scale.size, num_frames=scale.frames),
                              size=TRAIN_SCENES)
    batch_cfg = BatchConfig(global_batch=scale.batch, num_inputs=scale.num_inputs, num_targets=scale.num_targets,
                            with_depth=depth)
    losses, dropped = [], 0.0
    with BatchIterator(source, batch_cfg, seed=scale.seed, num_devices=n_dev) as batches:
        for _ in range(scale.steps):
            state, metrics = step(state, T.shard_for_pmap(next(batches), n_dev))
            metrics = jax.device_get(metrics)  # host copies: indexing device arrays compiles ops
            losses.append(float(metrics["loss"][0]))
            dropped += float(metrics["dropped"][0]) * n_dev
    params = jax.tree.map(lambda x: x[0], jax.device_get(state.params))  # NumPy, device 0's copy
    return Trained(params, np.asarray(losses, np.float32), time.perf_counter() - t0, int(dropped))


# --------------------------------------------------------------------------- evaluation


def eval_samples(scale: Scale, depth: bool) -> list[dict[str, np.ndarray]]:
    """Held-out procedural scenes (seeds ``EVAL_SEED + i``), each split as the paper
    evaluates: every 8th frame a target, k-means inputs over the rest. One sample per
    scene, with a leading batch axis of 1."""
    cfg = ProceduralConfig(height=scale.size, width=scale.size, num_frames=scale.frames)
    geom = ViewGeometry()
    samples = []
    for i in range(scale.eval_scenes):
        scene = procedural_scene(EVAL_SEED + i, cfg)
        inputs, targets = eval_views(scene.c2w, scale.num_inputs)
        s = make_sample(scene, inputs, targets, geom, with_depth=depth)
        samples.append({k: v[None] for k, v in s.items()})
    return samples


@functools.lru_cache(maxsize=None)
def _jitted(cfg: C.ModelConfig, size: int):
    """Jitted ``reconstruct``, ``render`` and per-target scores for ``cfg``, one set per
    ``(cfg, size)`` so evaluation and timing share their compilations."""
    recon = jax.jit(lambda p, s: reconstruct(p, cfg, s["input_images"], s["input_c2w"], s["input_intrinsics"]))
    rend = jax.jit(lambda p, g, c2w, k: render(p, cfg, g, c2w, k, size, size, cfg.outputs))

    def score(images: dict, s: dict, lpips_params: Any) -> dict:
        pred, gt = images["rgb"][0], s["target_images"][0]  # [T, H, W, 3]
        scores = {"psnr": psnr(pred, gt), "ssim": ssim(pred, gt)}
        if lpips_params is not None:
            scores["lpips"] = lpips(lpips_params, pred, gt)
        if "depth" in cfg.outputs:
            dm = depth_metrics(images["depth"][0, ..., 0], s["target_depth"][0])
            scores.update(abs_diff=dm["abs_diff"], delta_1_25=dm["delta_1_25"])
        return scores

    return recon, rend, jax.jit(score)


def evaluate(params: dict, cfg: C.ModelConfig, scale: Scale, samples: Sequence[dict],
             lpips_params: Any = None) -> dict[str, float]:
    """Mean PSNR / SSIM (/ LPIPS with ``lpips_params``) over every target of ``samples``,
    plus depth Abs Diff and delta < 1.25 when ``cfg`` renders depth, and ``eval_dropped``
    (splat intersections lost to capacity, summed)."""
    recon, rend, score = _jitted(cfg, scale.size)
    scores: dict[str, list[np.ndarray]] = {}
    dropped = 0
    for s in samples:
        out = rend(params, recon(params, s), s["target_c2w"], s["target_intrinsics"])
        for k, v in jax.device_get(score(out.images, s, lpips_params)).items():
            scores.setdefault(k, []).append(v)
        dropped += int(np.sum(out.dropped))
    result = {k: float(np.nanmean(np.concatenate(v))) for k, v in scores.items()}
    result["eval_dropped"] = dropped
    return result


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
    recon, rend, _ = _jitted(cfg, scale.size)
    g = recon(params, sample)
    n_targets = sample["target_c2w"].shape[1]
    return {
        "gaussians": int(g.means.shape[1]),
        "recon_s": _median_seconds(lambda: recon(params, sample), scale.timing_repeats),
        "render_s": _median_seconds(lambda: rend(params, g, sample["target_c2w"], sample["target_intrinsics"]),
                                    scale.timing_repeats) / n_targets,
    }


# ------------------------------------------------------------------------------- tables


def run_table(variants: Sequence[Variant], scale: Scale) -> list[dict[str, Any]]:
    """Train, evaluate and time each selected row (:func:`selected`); rows without a
    config are kept with ``status`` saying why. One result dict per row: its labels,
    ``paper`` numbers, ``status``, and for run rows ``params``, ``decoder_params``,
    ``decoder_dim`` (None in colour mode), ``train_s``, ``final_loss``, ``train_dropped``, the :func:`evaluate` scores and the
    :func:`time_model` timings."""
    rows = selected(variants)
    runnable = any(v.build is not None for _, v in rows)
    samples = eval_samples(scale, "depth" in scale.base.outputs) if runnable else []
    lp = load_lpips_params() if scale.lpips and runnable else None
    results = []
    for index, v in rows:
        row: dict[str, Any] = {"row": index, **v.labels, "chosen": v.chosen, "paper": dict(v.paper)}
        if v.build is None:
            results.append({**row, "status": f"not run: {v.note}"})
            continue
        cfg = v.build(scale.base)
        trained = train(cfg, scale, v)
        tail = trained.losses[-max(1, len(trained.losses) // 10):]
        row.update(
            status="ok",
            params=count_params(trained.params),
            decoder_params=count_params(trained.params.get("decoder", {})),
            decoder_dim=cfg.decoder.dim if cfg.head.mode == "feature" else None,
            train_s=trained.seconds,
            final_loss=float(np.mean(tail)) if len(tail) else float("nan"),
            train_dropped=trained.dropped,
        )
        row.update(evaluate(trained.params, cfg, scale, samples, lp))
        row.update(time_model(trained.params, cfg, scale, samples[0]))
        results.append(row)
        print(f"row {index} {v.labels}: {row['status']}, PSNR {row['psnr']:.2f}, {row['train_s']:.0f} s", flush=True)
    return results


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
    for ms)."""

    key: str
    title: str
    digits: int = 2
    scale: float = 1.0


def format_table(results: Sequence[dict[str, Any]], label_keys: Sequence[str],
                 columns: Sequence[Column] = ()) -> str:
    """A Markdown table: one line per result, the label columns, then ``columns``;
    ``*`` marks the paper's chosen row, rows that did not run show their status."""
    head = ["", *label_keys, *[c.title for c in columns]]
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for r in results:
        cells = ["*" if r["chosen"] else "", *[str(r[k]) for k in label_keys]]
        for c in columns:
            if c.key.startswith("paper:"):
                cells.append(r["paper"].get(c.key[6:], "-"))
            else:
                value = r.get(c.key)
                if isinstance(value, float):
                    value = value * c.scale
                cells.append(_fmt(value, c.digits) if r["status"] == "ok" else "-")
        lines.append("| " + " | ".join(cells) + " |")
    notes = [f"row {r['row']}: {r['status']}" for r in results if r["status"] != "ok"]
    return "\n".join(lines + ([""] + notes if notes else []))
