"""Evaluation diagnostics (input-view re-render PSNR, Gaussian statistics) and the refined rows, against NumPy."""

from dataclasses import replace

import jax
import numpy as np
import pytest

from llrmpp_jax import config as C
from llrmpp_jax.evaluate import evaluate, summary_table
from llrmpp_jax.metrics import load_lpips_params
from llrmpp_jax.model import init_params, reconstruct, render
from llrmpp_jax.refine import RefineConfig, refine


def _camera(x: float, yaw: float) -> np.ndarray:
    c, s = np.cos(yaw), np.sin(yaw)
    m = np.eye(4, dtype=np.float32)
    m[:3, :3] = [[c, 0, s], [0, 1, 0], [-s, 0, c]]
    m[0, 3] = x
    return m


def _setup():
    """A tiny model with a perturbed head and one random two-view sample (cfg, params, sample)."""
    # Opacity bias -4.6 puts sigmoid(bias) at ~0.01, so with a perturbed head the
    # opacities straddle the 0.01 threshold and the fraction is neither 0 nor 1.
    cfg = replace(C.tiny(), head=replace(C.tiny().head, max_dist=4.0, scale_bias=-3.0, opacity_bias=-4.6))
    v, h, w = 2, 16, 16
    params = init_params(jax.random.key(0), cfg, v, h, w)
    proj = params["head"]["proj"]["kernel"]
    params["head"]["proj"]["kernel"] = proj + 0.3 * jax.random.normal(jax.random.key(1), proj.shape, proj.dtype)
    rng = np.random.default_rng(0)
    sample = {
        "input_images": rng.uniform(0.05, 0.95, (v, h, w, 3)).astype(np.float32),
        "input_c2w": np.stack([_camera(-0.3, 0.1), _camera(0.3, -0.1)]),
        "input_intrinsics": np.array([[14.0, 15.0, 8.0, 8.0], [15.0, 14.0, 8.5, 7.5]], np.float32),
        "target_images": rng.uniform(0.05, 0.95, (1, h, w, 3)).astype(np.float32),
        "target_c2w": _camera(0.0, 0.3)[None],
        "target_intrinsics": np.array([[14.5, 14.5, 8.0, 8.0]], np.float32),
    }
    return cfg, params, sample


def _psnr(rgb, target) -> float:
    """Mean over views of the PSNR of clipped ``rgb`` [V, H, W, 3], in float64."""
    err = (np.clip(np.asarray(rgb, np.float64), 0, 1) - target) ** 2
    return float(np.mean(-10 * np.log10(err.mean(axis=(1, 2, 3)))))


def test_model_row_diagnostics_match_numpy():
    cfg, params, sample = _setup()
    h, w = sample["input_images"].shape[1:3]
    rows, summary, _ = evaluate(params, cfg, [sample])
    model = next(r for r in rows if r["method"] == "model")

    @jax.jit
    def rerender(params, b):
        g = reconstruct(params, cfg, b["input_images"], b["input_c2w"], b["input_intrinsics"])
        return g, render(params, cfg, g, b["input_c2w"], b["input_intrinsics"], h, w).images["rgb"]

    g, again = rerender(params, {k: x[None] for k, x in sample.items()})
    want_psnr = _psnr(again[0], sample["input_images"])
    opac = np.asarray(g.opacities, np.float64)
    np.testing.assert_allclose(model["input_psnr"], want_psnr, rtol=1e-4)
    np.testing.assert_allclose(model["mean_scale"], np.mean(np.asarray(g.scales, np.float64)), rtol=1e-5)
    np.testing.assert_allclose(model["mean_opacity"], opac.mean(), rtol=1e-5)
    np.testing.assert_allclose(model["opaque_fraction"], np.mean(opac > 0.01), atol=1e-6)
    assert 0.05 < model["opaque_fraction"] < 0.95
    assert summary["model"]["input_psnr"] == model["input_psnr"]
    # The baselines have no diagnostics: the table shows "-" there instead of failing.
    assert "input_psnr" not in summary["nearest_view"]
    head, _, *lines = [[c.strip() for c in ln.strip("|").split("|")] for ln in summary_table(summary).splitlines()]
    table = {ln[0]: dict(zip(head, ln)) for ln in lines}
    assert table["nearest_view"]["input_psnr"] == "-" and table["model"]["input_psnr"] == f"{model['input_psnr']:.4f}"


def test_refined_rows_are_refine_then_render():
    """``refine_steps``: a ``refined_<n>`` row per scene, equal to refine.refine's Gaussians
    rendered by model.render and scored in NumPy; its input views fit better than the model's."""
    cfg, params, sample = _setup()
    h, w = sample["input_images"].shape[1:3]
    rows, summary, _ = evaluate(params, cfg, [sample], refine_steps=4)
    assert [r["method"] for r in rows] == ["model", "refined_4", "mean_colour", "nearest_view"]
    assert list(summary) == ["model", "refined_4", "mean_colour", "nearest_view"]
    model, refined = rows[0], rows[1]

    b = {k: x[None] for k, x in sample.items()}
    g = reconstruct(params, cfg, b["input_images"], b["input_c2w"], b["input_intrinsics"])
    g, info = refine(params, cfg, g, b["input_images"], b["input_c2w"], b["input_intrinsics"], steps=4)
    assert info.steps == 4 and info.losses[-1] < info.losses[0]
    targets = render(params, cfg, g, b["target_c2w"], b["target_intrinsics"], h, w).images["rgb"]
    inputs = render(params, cfg, g, b["input_c2w"], b["input_intrinsics"], h, w).images["rgb"]
    np.testing.assert_allclose(refined["psnr"], _psnr(targets[0], sample["target_images"]), rtol=1e-4)
    np.testing.assert_allclose(refined["input_psnr"], _psnr(inputs[0], sample["input_images"]), rtol=1e-4)
    np.testing.assert_allclose(refined["mean_opacity"], np.mean(np.asarray(g.opacities, np.float64)), rtol=1e-5)
    assert refined["input_psnr"] > model["input_psnr"] + 0.01
    with pytest.raises(ValueError, match="refine_steps must be >= 0, got -1"):
        evaluate(params, cfg, [sample], refine_steps=-1)


def test_refined_rows_with_the_perceptual_term():
    """A perceptual refinement (``RefineConfig.perceptual_weight``) uses the LPIPS network's
    VGG16: the refined row equals refine.refine called with that VGG16, rendered and scored
    in NumPy; without LPIPS params to take it from, evaluate fails as refine does."""
    cfg, params, sample = _setup()
    h, w = sample["input_images"].shape[1:3]
    lpips_params, rc = load_lpips_params(), RefineConfig(perceptual_weight=0.5)
    rows, _, _ = evaluate(params, cfg, [sample], lpips_params, refine_steps=3, refine_config=rc)
    refined = rows[1]
    b = {k: x[None] for k, x in sample.items()}
    g = reconstruct(params, cfg, b["input_images"], b["input_c2w"], b["input_intrinsics"])
    g, info = refine(
        params,
        cfg,
        g,
        b["input_images"],
        b["input_c2w"],
        b["input_intrinsics"],
        steps=3,
        rc=rc,
        vgg_params=lpips_params["vgg"],
    )
    assert info.losses[-1] < info.losses[0]
    targets = render(params, cfg, g, b["target_c2w"], b["target_intrinsics"], h, w).images["rgb"]
    np.testing.assert_allclose(refined["psnr"], _psnr(targets[0], sample["target_images"]), rtol=1e-4)
    mse_only, _, _ = evaluate(params, cfg, [sample], lpips_params, refine_steps=3)
    assert abs(mse_only[1]["psnr"] - refined["psnr"]) > 1e-4  # the perceptual term changed the fit
    with pytest.raises(ValueError, match="perceptual_weight=0.5 needs vgg_params"):
        evaluate(params, cfg, [sample], refine_steps=3, refine_config=rc)
