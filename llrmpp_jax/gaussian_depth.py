"""Depth supervision of the Gaussians themselves (no decoder): where they sit, not what the
decoder paints.

The feature model's decoder can paint a target view from Gaussians in the wrong place (on
one scene it memorises target views, docs/lab-notes.md "First round"), so an RGB loss alone moves the
Gaussians slowly. Where ground-truth depth exists (procedural scenes, ScanNet++), this term
renders the Gaussians' expected camera z at the decoder's canvas resolution (gsplat's "ED":
accumulated z over accumulated alpha, as the colour model's depth in ``model.py``) and
applies the paper's depth loss (:func:`losses.depth_loss`) against the area-averaged ground
truth. It is Long-LRM's idea (its depth term supervises the colour Gaussians' centres, facts
§2.2) carried to feature Gaussians, an option of the experiment (``gaussian_depth_weight``),
off in the paper configs.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

from llrmpp_jax.array_typing import Array, ArrayLike, Float
from llrmpp_jax.config import ModelConfig
from llrmpp_jax.gaussians import Gaussians
from llrmpp_jax.losses import depth_loss
from llrmpp_jax.splat import SplatOutput, rasterize


def splat_depth_view(
    g: Gaussians,
    cfg: ModelConfig,
    camera: tuple[Float[ArrayLike, "4 4"], Float[ArrayLike, " 4"]],
    size: tuple[int, int],
) -> SplatOutput:
    """One scene's Gaussians (no batch axis, ``means [N, 3]``) splatted for depth at one
    ``camera = (c2w, intrinsics)`` on a ``size = (height, width)`` canvas (``splat.rasterize``
    in "ED" mode): ``out.depth [H, W]`` the expected camera z (0 where nothing was drawn),
    ``out.transmittance``. 3D or 2D Gaussians as the model's head predicts them
    (``cfg.head.primitive``, ``surfel_depth``)."""
    (c2w, intrinsics), (height, width) = camera, size
    return rasterize(
        g.means,
        g.quats,
        g.scales,
        g.opacities,
        None,
        c2w,
        intrinsics,
        height,
        width,
        cfg.splat,
        render_mode="ED",
        primitive=cfg.head.primitive,
        surfel_depth=cfg.head.splat_surfel_depth,
    )


def splatted_depth(
    g: Gaussians,
    c2w: Float[Array, "B T 4 4"],
    intrinsics: Float[Array, "B T 4"],
    height: int,
    width: int,
    cfg: ModelConfig,
) -> tuple[Float[Array, "B T H W"], Float[Array, "B T H W"]]:
    """Expected camera z (scene units) and accumulated alpha of the Gaussians at each target
    camera, ``height x width`` pixels (``intrinsics`` given at that size)."""

    def one(g, cam, k):
        out = splat_depth_view(g, cfg, (cam, k), (height, width))
        return out.depth, 1.0 - out.transmittance

    return jax.vmap(jax.vmap(one, (None, 0, 0)))(g, c2w, intrinsics)


def gaussian_depth_loss(
    g: Gaussians,
    target_c2w: Float[Array, "B T 4 4"],
    target_intrinsics: Float[Array, "B T 4"],
    target_depth: Float[Array, "B T H W"],
    cfg: ModelConfig,
) -> tuple[Float[Array, ""], dict[str, Float[Array, ""]]]:
    """The paper's depth loss on :func:`splatted_depth` at the canvas resolution
    ``H/r x W/r`` (r = the decoder's canvas ratio; 1 in colour mode) against the r x r area
    mean of ``target_depth`` (a block with any invalid pixel is masked).

    Returns ``(loss, aux)``, aux as :func:`losses.depth_loss` plus ``alpha``, the
    mean accumulated alpha (how much of the view the Gaussians cover)."""
    r = cfg.decoder.canvas_ratio if cfg.head.mode == "feature" else 1
    b, t, h, w = target_depth.shape
    if h % r or w % r:
        raise ValueError(f"gaussian_depth_loss: depth {h}x{w} is not a multiple of the canvas ratio {r}")
    blocks = target_depth.reshape(b, t, h // r, r, w // r, r)
    valid = jnp.all(jnp.isfinite(blocks) & (blocks > 0), axis=(3, 5))
    gt = jnp.where(valid, jnp.mean(jnp.where(jnp.isfinite(blocks), blocks, 0.0), axis=(3, 5)), 0.0)
    k = target_intrinsics / r  # (fx, fy, cx, cy) at the canvas size
    pred, alpha = splatted_depth(g, target_c2w, k, h // r, w // r, cfg)
    loss, aux = depth_loss(pred, gt, k)
    return loss, dict(aux, alpha=jnp.mean(alpha))
