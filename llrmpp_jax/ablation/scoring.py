"""Scoring a row on held-out procedural scenes: :func:`eval_samples`, :func:`evaluate`
(PSNR, SSIM, LPIPS, depth), :func:`time_model` (reconstruct and render times) and
:func:`references` (the untrained row and two baselines, what a row must beat)."""

from __future__ import annotations

import functools
import time
from collections.abc import Callable, Sequence
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from llrmpp_jax import config as C
from llrmpp_jax.ablation.scales import EVAL_SEED, Scale
from llrmpp_jax.ablation.stats import summarise
from llrmpp_jax.ablation.training import init_model
from llrmpp_jax.data import ProceduralConfig, ViewGeometry, eval_views, make_sample, procedural_scene, training_views
from llrmpp_jax.evaluate import baseline_predictions
from llrmpp_jax.metrics import depth_metrics, lpips, psnr, ssim
from llrmpp_jax.model import reconstruct, render

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


def references(cfg: C.ModelConfig, scale: Scale, samples: Sequence[dict], lpips_params: Any = None
               ) -> list[dict[str, Any]]:
    """What a row must beat, on the held-out ``samples``: ``cfg`` untrained (one init per
    seed) and the two baselines of :func:`llrmpp_jax.evaluate.baseline_predictions`
    (mean input colour; the input view nearest each target, shown as-is)."""
    untrained = [evaluate(init_model(cfg, scale, seed), cfg, scale, samples, lpips_params)
                 for seed in range(scale.seeds)]
    rows = [{"name": "untrained", **summarise(untrained)}]
    for method in ("mean_colour", "nearest_view"):
        scores = []
        for s in samples:
            pred = baseline_predictions({k: v[0] for k, v in s.items()})[method]
            scores.append(jax.device_get(_jitted_score(jnp.asarray(pred)[None], s, lpips_params, None)))
        rows.append({"name": method.replace("_", " "), **_mean_scores(scores)})
    return rows
