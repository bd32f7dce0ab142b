"""Bake feature Gaussians into standard 3DGS colour Gaussians, so any 3DGS viewer shows
the scene (``llrmpp export --bake``).

A feature-mode scene needs the model's decoder to be seen. :func:`bake_colour` fits
colour Gaussians with spherical harmonics of degree ``sh_degree`` to what the model itself
renders -- its decoded RGB at the input cameras and at cameras between them on a spline
through them in capture order -- with the
refinement's machinery (:func:`llrmpp_jax.refine.refine`: optimistix around one Adam per
field, a random subset of the views per update). Geometry starts from the feature Gaussians
-- means and rotations as they are, scales widened by the model's canvas footprint
(:func:`canvas_footprint_scales`) -- and is fitted too (``geometry=False`` keeps it: on a
procedural scene that cost several dB against the model's renders on held-out views, as the feature
Gaussians alone leave gaps the decoder fills); the opacity starts
at the feature Gaussian's total opacity (the partitions' opacities sum to it) and is fitted,
and the colour starts at the mean of the model's rendered colour where the Gaussian's centre
lands in the fitted views (occlusion ignored: the fit corrects it; grey where it lands in none).

What baking costs is measured on the held-out target views, which the fit never sees:
PSNR of the baked renders against the model's renders, and against the photos beside the
model's own PSNR against them.
"""

from __future__ import annotations

import dataclasses
import time
from dataclasses import dataclass

import jax
import jax.numpy as jnp
import numpy as np

from llrmpp_jax.array_typing import Float
from llrmpp_jax.capture.render import frame_photos, render_views, spline_at
from llrmpp_jax.capture.scene_file import SavedScene
from llrmpp_jax.config import ModelConfig
from llrmpp_jax.errors import UserError
from llrmpp_jax.gaussians import Gaussians
from llrmpp_jax.metrics import psnr
from llrmpp_jax.refine import RefineConfig, RefineInfo, refine
from llrmpp_jax.splat.sh import MAX_DEGREE, SH_C0, num_sh_bases


@dataclass(frozen=True)
class BakeConfig:
    """How :func:`bake_colour` fits. ``rate_scale`` multiplies :class:`RefineConfig`'s
    per-field rates (SH from grey needs larger steps than a refinement's nudges)."""

    sh_degree: int = 3
    steps: int = 300
    views_per_step: int = 4
    views_between: int = 2  # views between each two consecutive inputs (spline), fitted besides them
    geometry: bool = True  # fit means, rotations and scales too (False: keep the model's)
    rate_scale: float = 2.0

    def __post_init__(self) -> None:
        if not 0 <= self.sh_degree <= MAX_DEGREE:
            raise UserError(f"--sh-degree must be in 0..{MAX_DEGREE}, got {self.sh_degree}")
        if self.steps < 1 or self.views_per_step < 1 or self.views_between < 0:
            raise UserError(
                f"bake needs steps >= 1, views per step >= 1 and views between >= 0, got "
                f"{self.steps}, {self.views_per_step}, {self.views_between}"
            )


@dataclass(frozen=True)
class Baked:
    """:func:`bake_colour`'s result: one scene's colour Gaussians (no batch axis, scene
    frame), the colour-mode config that renders them, and the held-out scores (dB)."""

    gaussians: Gaussians
    cfg: ModelConfig
    psnr_vs_model: float  # baked renders vs the model's renders, held-out targets
    psnr_baked_vs_photos: float  # baked renders vs the photos, held-out targets (nan: none)
    psnr_model_vs_photos: float  # the model's renders vs the photos, the same views
    fit_views: int
    info: RefineInfo
    seconds: float

    def lines(self) -> list[str]:
        out = [
            f"baked {self.gaussians.means.shape[0]:,} Gaussians to SH degree {self.cfg.head.sh_degree} in "
            f"{self.info.steps} updates of {self.info.views_per_step}/{self.fit_views} views ({self.seconds:.0f} s); "
            f"fitted views {self.info_psnr(0):.2f} -> {self.info_psnr(-1):.2f} dB"
        ]
        if np.isfinite(self.psnr_vs_model):
            out.append(f"held-out views: baked vs the model's renders {self.psnr_vs_model:.2f} dB")
        if np.isfinite(self.psnr_baked_vs_photos):
            out.append(
                f"held-out photos: baked {self.psnr_baked_vs_photos:.2f} dB, the model "
                f"{self.psnr_model_vs_photos:.2f} dB (baking costs "
                f"{self.psnr_model_vs_photos - self.psnr_baked_vs_photos:.2f} dB)"
            )
        return out

    def info_psnr(self, i: int) -> float:
        """PSNR (dB) of the first update's views from the fit's MSE loss, before (0) or
        after (-1) the fit."""
        return float(-10.0 * np.log10(max(float(self.info.losses[i]), 1e-12)))


def colour_config(cfg: ModelConfig, sh_degree: int) -> ModelConfig:
    """``cfg`` rendering colour Gaussians with SH of ``sh_degree`` (same splatter and
    background)."""
    return dataclasses.replace(cfg, head=dataclasses.replace(cfg.head, mode="color", sh_degree=sh_degree))


def _renders(params, saved: SavedScene, c2w: np.ndarray, intrinsics: np.ndarray) -> jax.Array:
    """``[V, H, W, 3]`` RGB renders in [0, 1] of ``saved`` at these cameras."""
    return jnp.asarray(render_views(params, saved, c2w, intrinsics, [""] * len(c2w), progress=False).rgb)


def initial_colours(
    means: Float[np.ndarray, "N 3"],
    c2w: Float[np.ndarray, "V 4 4"],
    intrinsics: Float[np.ndarray, "V 4"],
    images: Float[np.ndarray, "V H W 3"],
) -> Float[np.ndarray, "N 3"]:
    """Mean colour of the pixels each centre projects to over the views in front of it and
    inside the frame (OpenCV cameras, pixel centres at +0.5); 0.5 grey where there are none."""
    w2c = np.linalg.inv(c2w.astype(np.float64))
    cam = np.einsum("vij,nj->vni", w2c[:, :3, :3], means) + w2c[:, None, :3, 3]
    z = cam[..., 2]
    h, w = images.shape[1:3]
    with np.errstate(divide="ignore", invalid="ignore"):
        u = intrinsics[:, None, 0] * cam[..., 0] / z + intrinsics[:, None, 2]
        v = intrinsics[:, None, 1] * cam[..., 1] / z + intrinsics[:, None, 3]
    seen = (z > 0) & (u >= 0) & (u < w) & (v >= 0) & (v < h)
    ui = np.clip(np.nan_to_num(u), 0, w - 1).astype(np.int64)
    vi = np.clip(np.nan_to_num(v), 0, h - 1).astype(np.int64)
    colours = images[np.arange(len(images))[:, None], vi, ui]  # [V, N, 3]
    count = seen.sum(0)[:, None]
    total = np.where(seen[..., None], colours, 0.0).sum(0)
    return np.where(count > 0, total / np.maximum(count, 1), 0.5)


def canvas_footprint_scales(
    gaussians: Gaussians, c2w: Float[np.ndarray, "V 4 4"], intrinsics: Float[np.ndarray, "V 4"], cfg: ModelConfig
) -> Float[np.ndarray, "N 3"]:
    """Scales that draw at full resolution as wide as the model drew them on its canvas.

    The model splats onto a canvas ``canvas_ratio`` = r times coarser than the image, and the
    splatter's ``eps2d`` dilation (in canvas pixels) there is r^2 times the same dilation in
    image pixels. So each scale gets the missing variance ``eps2d (r^2 - 1)`` image pixels^2,
    in world units at the Gaussian's median depth over the views (one isotropic term, as
    the dilation is)."""
    r = cfg.decoder.canvas_ratio
    means = np.asarray(gaussians.means, np.float64)
    w2c = np.linalg.inv(c2w.astype(np.float64))
    z = np.einsum("vj,nj->vn", w2c[:, 2, :3], means) + w2c[:, None, 2, 3]
    z = np.where(z > 0, z, np.nan)
    pixel = np.nanmedian(z / intrinsics[:, None, 0], axis=0)  # world units per image pixel
    pixel = np.nan_to_num(pixel, nan=0.0)
    extra = cfg.splat.eps2d * (r * r - 1) * pixel**2
    return np.sqrt(np.square(np.asarray(gaussians.scales, np.float64)) + extra[:, None]).astype(np.float32)


def views_between(saved: SavedScene, per_gap: int) -> tuple[Float[np.ndarray, "V 4 4"], Float[np.ndarray, "V 4"]]:
    """``(c2w, intrinsics)`` of ``per_gap`` cameras between each two consecutive inputs (capture
    order), evenly in the parameter of the spline through them (:func:`spline_at`: at
    ``i + j / (per_gap + 1)``), with the inputs' mean intrinsics. Fitting the bake at these
    views as well as the inputs brings its renders of held-out views closer to the model's
    (docs/lab-notes.md, "Baking feature Gaussians into colour Gaussians")."""
    inputs = saved.c2w[saved.inputs]
    if per_gap == 0 or len(inputs) < 2:
        return np.zeros((0, 4, 4)), np.zeros((0, 4))
    fractions = np.arange(1, per_gap + 1) / (per_gap + 1)
    positions = (np.arange(len(inputs) - 1)[:, None] + fractions[None, :]).reshape(-1)
    k = np.broadcast_to(saved.intrinsics[saved.inputs].mean(0), (len(positions), 4)).copy()
    return spline_at(inputs, positions), k


def bake_colour(
    params: dict,
    saved: SavedScene,
    bake: BakeConfig = BakeConfig(),
    progress: bool = False,
    scene_path: str | None = None,
) -> Baked:
    """Colour Gaussians that render like the feature-mode ``saved`` scene (module
    docstring). ``params``: the model that made it (its decoder renders the targets);
    ``scene_path``: where the photos are (default: the path in the .gs file), for the
    held-out scores against them."""
    if saved.model.head.mode != "feature":
        raise UserError("bake: the scene is already in colour mode; export it without --bake")
    t0 = time.perf_counter()
    feature_g = jax.tree.map(lambda x: jnp.asarray(x)[None], saved.gaussians)
    path_c2w, path_intr = views_between(saved, bake.views_between)
    c2w = np.concatenate([saved.c2w[saved.inputs], path_c2w]).astype(np.float32)
    intr = np.concatenate([saved.intrinsics[saved.inputs], path_intr]).astype(np.float32)
    targets = _renders(params, saved, c2w, intr)

    cfg = colour_config(saved.model, bake.sh_degree)
    n = feature_g.means.shape[1]
    dc = (initial_colours(np.asarray(saved.gaussians.means), c2w, intr, np.asarray(targets)) - 0.5) / SH_C0
    features = np.zeros((1, n, num_sh_bases(bake.sh_degree) * 3), np.float32)
    features[0, :, :3] = dc
    scales = canvas_footprint_scales(saved.gaussians, c2w, intr, saved.model)
    colour_g = feature_g._replace(features=jnp.asarray(features), scales=jnp.asarray(scales)[None])
    still = 0.0 if not bake.geometry else 1.0
    base = RefineConfig()
    rc = RefineConfig(
        lr_means=base.lr_means * still,
        lr_log_scales=base.lr_log_scales * still,
        lr_quats=base.lr_quats * still,
        rate_scale=bake.rate_scale,
        views_per_step=bake.views_per_step,
    )
    baked, info = refine(
        {},
        cfg,
        colour_g,
        targets[None],
        jnp.asarray(c2w)[None],
        jnp.asarray(intr)[None],
        steps=bake.steps,
        rc=rc,
        progress=progress,
    )

    baked_scene = dataclasses.replace(saved, model=cfg, gaussians=jax.tree.map(lambda x: np.asarray(x[0]), baked))
    vs_model = baked_vs_photos = model_vs_photos = float("nan")
    if len(saved.targets):
        t_c2w, t_intr = saved.c2w[saved.targets], saved.intrinsics[saved.targets]
        model_rgb = _renders(params, saved, t_c2w, t_intr)
        baked_rgb = _renders({}, baked_scene, t_c2w, t_intr)
        vs_model = float(jnp.mean(psnr(baked_rgb, model_rgb)))
        try:
            photos = jnp.asarray(frame_photos(saved, saved.targets, scene_path))
        except (OSError, UserError):  # the capture moved: the scores against the model remain
            photos = None
        if photos is not None:
            baked_vs_photos = float(jnp.mean(psnr(baked_rgb, photos)))
            model_vs_photos = float(jnp.mean(psnr(model_rgb, photos)))
    return Baked(
        baked_scene.gaussians, cfg, vs_model, baked_vs_photos, model_vs_photos, len(c2w), info, time.perf_counter() - t0
    )
