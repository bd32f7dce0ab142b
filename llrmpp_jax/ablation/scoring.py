"""Scoring a row on held-out procedural scenes with ``llrmpp train``'s own evaluation: the
row is its experiment (:func:`~llrmpp_jax.ablation.training.row_experiment`) with the
scale's held-out scenes (:func:`held_out_experiment`), its samples are
:func:`llrmpp_jax.experiment_data.eval_samples` of that experiment (:func:`held_out_samples`)
and its scores :func:`llrmpp_jax.evaluate.evaluate`'s (:func:`row_scores`: PSNR, SSIM,
LPIPS, depth, diagnostics). :func:`time_model` (reconstruct and render times) and
:func:`references` (the untrained row and two baselines, what a row must beat)."""

from __future__ import annotations

import dataclasses
import time
from collections.abc import Callable, Sequence
from typing import Any

import jax
import numpy as np

from llrmpp_jax import config as C
from llrmpp_jax.ablation.scales import EVAL_SEED, Scale
from llrmpp_jax.ablation.stats import summarise
from llrmpp_jax.ablation.training import init_model, row_experiment
from llrmpp_jax.evaluate import evaluate, predicted_gaussians, render_sample
from llrmpp_jax.experiment import ExperimentConfig
from llrmpp_jax.experiment_data import eval_samples

BASELINES = {"mean_colour": "mean colour", "nearest_view": "nearest view"}  # evaluate's method -> reference name


def held_out_experiment(cfg: C.ModelConfig, scale: Scale) -> ExperimentConfig:
    """The row's experiment with the scale's held-out scenes: ``scale.eval_scenes``
    procedural scenes from seed :data:`~llrmpp_jax.ablation.scales.EVAL_SEED`, their views
    the paper's split (``scale.eval_span`` None: every 8th frame a target, k-means inputs
    over the rest) or one draw of the training view sampler in ``eval_span``-frame windows,
    the same views at every training seed (paired seeds)."""
    exp = row_experiment(cfg, scale)
    data = dataclasses.replace(
        exp.data,
        eval_seed_offset=EVAL_SEED,
        num_eval_scenes=scale.eval_scenes,
        eval_span=scale.eval_span,
        eval_views_follow_seed=False,
        procedural_eval="split" if scale.eval_span is None else "window",
    )
    return dataclasses.replace(exp, data=data)


def held_out_samples(cfg: C.ModelConfig, scale: Scale) -> list[dict[str, np.ndarray]]:
    """The unbatched held-out samples a row of ``cfg`` is scored on:
    :func:`~llrmpp_jax.experiment_data.eval_samples` of :func:`held_out_experiment`."""
    exp = held_out_experiment(cfg, scale)
    return eval_samples(exp, exp.stages[0])[0]


def row_scores(params: dict, cfg: C.ModelConfig, samples: Sequence[dict], lpips_params: Any = None) -> dict[str, float]:
    """The model's summary of :func:`llrmpp_jax.evaluate.evaluate` on ``samples`` (PSNR,
    SSIM, LPIPS with ``lpips_params``, the depth metrics when ``cfg`` renders depth, the
    diagnostics), plus ``eval_dropped``: splat intersections lost to capacity over every
    held-out target, summed."""
    rows, summary, _ = evaluate(params, cfg, samples, lpips_params)
    return _model_scores(rows, summary)


def _model_scores(rows: Sequence[dict], summary: dict[str, dict[str, float]]) -> dict[str, float]:
    """The model's summary of one :func:`~llrmpp_jax.evaluate.evaluate` with ``eval_dropped``
    (its rows' ``splat_dropped`` summed)."""
    dropped = sum(r["splat_dropped"] for r in rows if r["method"] == "model")
    return {**summary["model"], "eval_dropped": int(dropped)}


def _median_seconds(fn: Callable[[], Any], repeats: int) -> float:
    jax.block_until_ready(fn())  # compile + warm up
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        jax.block_until_ready(fn())
        times.append(time.perf_counter() - t0)
    return float(np.median(times))


def time_model(params: dict, cfg: C.ModelConfig, scale: Scale, sample: dict) -> dict[str, float]:
    """Median wall-clock seconds of the evaluation's reconstruction (one unbatched
    ``sample``: :func:`~llrmpp_jax.evaluate.predicted_gaussians`) and of its render per
    target frame (all outputs, splat + decode), after compilation; ``gaussians`` per scene."""
    batch = {k: v[None] for k, v in sample.items()}
    g, _ = predicted_gaussians(params, cfg, batch, None)
    n_targets = sample["target_c2w"].shape[0]
    return {
        "gaussians": int(g.means.shape[1]),
        "recon_s": _median_seconds(lambda: predicted_gaussians(params, cfg, batch, None), scale.timing_repeats),
        "render_s": _median_seconds(lambda: render_sample(params, cfg, g, batch, False), scale.timing_repeats)
        / n_targets,
    }


def references(
    cfg: C.ModelConfig, scale: Scale, samples: Sequence[dict], lpips_params: Any = None
) -> list[dict[str, Any]]:
    """What a row must beat, on the held-out ``samples``: ``cfg`` untrained (one init per
    seed, :func:`row_scores`) and the two baselines :func:`llrmpp_jax.evaluate.evaluate`
    scores beside the model (mean input colour; the input view nearest each target, shown
    as-is)."""
    untrained, baselines = [], {}
    for seed in range(scale.seeds):
        rows, summary, _ = evaluate(init_model(cfg, scale, seed), cfg, samples, lpips_params)
        untrained.append(_model_scores(rows, summary))
        baselines = {name: summary[method] for method, name in BASELINES.items()}  # the same at every seed
    return [{"name": "untrained", **summarise(untrained)}] + [{"name": n, **s} for n, s in baselines.items()]
