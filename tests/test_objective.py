"""The one training objective (llrmpp_jax.objective): its users compute the same loss.

* The trainer's (``make_loss_fn`` of an experiment) and the ablation notebooks' (a row's
  objective) agree on one batch, and both equal the loss composed here from its terms
  (``rgb_loss`` + ``depth_loss``, the oracle).
* Every weight of ``LossWeights`` scales its own term (depth, its gradient and normal
  terms, the Gaussians' own depth), as the overfit benchmark sets them.

Inputs are fresh random draws (images, cameras, depths in [0.5, 4)); tolerance 1e-6
relative (float32: the same ops on the same values, so equal up to XLA's fusion order).
"""

from dataclasses import replace

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from llrmpp_jax import ablation
from llrmpp_jax import config as C
from llrmpp_jax.experiment import ExperimentConfig, StageConfig
from llrmpp_jax.gaussian_depth import gaussian_depth_loss
from llrmpp_jax.losses import depth_loss, rgb_loss
from llrmpp_jax.model import init_params, reconstruct, render
from llrmpp_jax.objective import LossWeights, make_loss_fn, make_objective
from llrmpp_jax.pruning import prune_gaussians
from tests.helpers.scenes import orbit_scene

SIZE = 32  # the depth loss's coarsest gradient scale needs 32 pixels (the Gaussians' depth: a 32-pixel canvas)


def _depth_model() -> C.ModelConfig:
    return replace(
        C.tiny(),
        outputs=("rgb", "depth"),
        head=C.GaussianHeadConfig(gaussians_per_token=4, feature_dim=16, max_dist=4.0, scale_bias=-3.0),
    )


def _batch(key, size: int = SIZE) -> dict:
    """One scene: 2 input and 2 target views of ``size`` x ``size`` with random colours and
    ground-truth depth."""
    k_scene, k_depth = jax.random.split(key)
    images, c2w, intr = orbit_scene(k_scene, 1, 4, size, size)
    depth = jax.random.uniform(k_depth, (1, 2, size, size), jnp.float32, 0.5, 4.0)
    return {
        "input_images": images[:, :2],
        "input_c2w": c2w[:, :2],
        "input_intrinsics": intr[:, :2],
        "target_images": images[:, 2:],
        "target_c2w": c2w[:, 2:],
        "target_intrinsics": intr[:, 2:],
        "target_depth": depth,
    }


def _terms(params, cfg, batch, grad_weight, normal_weight, gaussian_depth=False):
    """The oracle: the RGB loss and the depth loss of the rendered targets, and with
    ``gaussian_depth`` the Gaussians' depth loss (else None), each from its own function."""
    g = reconstruct(params, cfg, batch["input_images"], batch["input_c2w"], batch["input_intrinsics"])
    h, w = batch["target_images"].shape[2:4]
    out = render(params, cfg, g, batch["target_c2w"], batch["target_intrinsics"], h, w, cfg.outputs)
    rgb, _ = rgb_loss(out.images["rgb"], batch["target_images"], None, perceptual_weight=0.0)
    depth, _ = depth_loss(
        out.images["depth"][..., 0],
        batch["target_depth"],
        batch["target_intrinsics"],
        grad_weight=grad_weight,
        normal_weight=normal_weight,
    )
    gdepth = None
    if gaussian_depth:
        gdepth, _ = gaussian_depth_loss(g, batch["target_c2w"], batch["target_intrinsics"], batch["target_depth"], cfg)
    return rgb, depth, gdepth


def test_notebook_and_trainer_objectives_agree(key):
    cfg = _depth_model()
    k_params, k_batch, k_loss = jax.random.split(key, 3)
    params, batch = init_params(k_params, cfg, 2, SIZE, SIZE), _batch(k_batch)
    grad_w, normal_w = 0.2, 0.05
    exp = ExperimentConfig(
        "t",
        cfg,
        (StageConfig("s", 1, 1, 2, 2, SIZE),),
        perceptual_weight=0.0,
        depth_grad_weight=grad_w,
        depth_normal_weight=normal_w,
    )
    trainer_loss = make_loss_fn(exp, None, exp.stages[0])
    scale = ablation.make_scale("smoke", paper_views=2, depth=True)
    assert scale.size == SIZE and scale.perceptual_weight == 0.0
    notebook_loss = ablation.row_objective(cfg, scale, grad_w, normal_w, None)

    @jax.jit
    def losses(params, batch, k):
        rgb, depth, _ = _terms(params, cfg, batch, grad_w, normal_w)
        return trainer_loss(params, batch, k)[0], notebook_loss(params, batch, k)[0], rgb + depth

    trainer, notebook, oracle = (float(x) for x in losses(params, batch, k_loss))
    assert np.isfinite(oracle) and oracle > 0
    np.testing.assert_allclose(trainer, oracle, rtol=1e-6)
    np.testing.assert_allclose(notebook, oracle, rtol=1e-6)


def test_each_weight_scales_its_term(key):
    """``depth``, ``depth_grad`` / ``depth_normal`` and ``gaussian_depth`` as the overfit
    benchmark sets them: loss = rgb + depth * depth_loss(grad, normal) + gaussian_depth * its
    loss; a ``depth`` weight of 0 leaves the depth head rendered but untrained."""
    cfg = _depth_model()
    k_params, k_batch, k_loss = jax.random.split(key, 3)
    params, batch = init_params(k_params, cfg, 2, 2 * SIZE, 2 * SIZE), _batch(k_batch, 2 * SIZE)
    weighted = make_objective(cfg, LossWeights(depth=0.5, depth_grad=0.3, depth_normal=0.2, gaussian_depth=0.25))
    rgb_only = make_objective(cfg, LossWeights(depth=0.0))

    @jax.jit
    def losses(params, batch, k):
        rgb, depth, gdepth = _terms(params, cfg, batch, 0.3, 0.2, gaussian_depth=True)
        (w, aux), (r, _) = weighted(params, batch, k), rgb_only(params, batch, k)
        return w, r, rgb + 0.5 * depth + 0.25 * gdepth, rgb, aux  # pyright: ignore[reportOperatorIssue] -- gaussian_depth=True gives the Gaussian depth term

    w, r, want_w, want_r, aux = losses(params, batch, k_loss)
    np.testing.assert_allclose(float(w), float(want_w), rtol=1e-6)
    np.testing.assert_allclose(float(r), float(want_r), rtol=1e-6)
    assert float(aux["depth_depth"]) > 0 and float(aux["gaussian_depth_depth"]) > 0
    assert {"mse", "psnr", "splat_dropped", "gaussian_usage"} <= set(aux)


def test_opacity_term_and_a_stage_s_pruning(key):
    """Long-LRM's recipe: loss = MSE + 0.1 x the mean opacity of the Gaussians rendered; a
    stage that sets pruning 0.6 / 0.1 trains the pruned set (the same parameters), the
    others the whole one. Oracle: reconstruct, prune_gaussians with the same key, render,
    rgb_loss, each from its own function (rtol 1e-6)."""
    cfg = replace(C.tiny(), head=C.GaussianHeadConfig(mode="color", sh_degree=1, max_dist=4.0, scale_bias=-3.0))
    k_params, k_batch, k_loss = jax.random.split(key, 3)
    params, batch = init_params(k_params, cfg, 2, 16, 16), _batch(k_batch, 16)
    plain = StageConfig("plain", 1, 1, 2, 2, 16)
    pruned = StageConfig("pruned", 1, 1, 2, 2, 16, prune_ratio=0.6, prune_random_ratio=0.1)
    exp = ExperimentConfig("t", cfg, (plain, pruned), perceptual_weight=0.0, opacity_weight=0.1)
    assert exp.model_of(plain) == cfg and exp.model_of(pruned).head.prune_ratio == 0.6

    @jax.jit
    def losses(params, batch, k):
        g = reconstruct(params, cfg, batch["input_images"], batch["input_c2w"], batch["input_intrinsics"])
        want = []
        for gs in (g, prune_gaussians(g, 0.6, 0.1, k)):
            out = render(params, cfg, gs, batch["target_c2w"], batch["target_intrinsics"], 16, 16)
            mse, _ = rgb_loss(out.images["rgb"], batch["target_images"], None, perceptual_weight=0.0)
            want.append((mse + 0.1 * jnp.mean(gs.opacities), jnp.mean(gs.opacities)))
        got = [make_loss_fn(exp, None, s)(params, batch, k) for s in (plain, pruned)]
        return [(loss, aux["opacity"]) for loss, aux in got], want

    got, want = losses(params, batch, k_loss)
    for (loss, opacity), (want_loss, want_opacity) in zip(got, want, strict=True):
        assert 0 < float(want_opacity) < 1
        np.testing.assert_allclose(float(opacity), float(want_opacity), rtol=1e-6)
        np.testing.assert_allclose(float(loss), float(want_loss), rtol=1e-6)
    assert abs(float(want[0][1]) - float(want[1][1])) > 1e-4  # pruning kept the more opaque ones
    with pytest.raises(ValueError, match=r"stage 'pruned': GaussianHeadConfig: pruning is Long-LRM's colour-mode"):
        ExperimentConfig("t", C.tiny(), (pruned,))
