"""Refine a saved capture's Gaussians against its input photos and score the held-out views
before and after (what ``llrmpp refine`` runs).

The photos are re-read from the capture (:func:`~.render.frame_photos`), brought to the
reconstruction's view size; the fit is :func:`llrmpp_jax.refine.refine` (the paper's
post-prediction optimisation); the score is the mean PSNR over the held-out targets
(:func:`llrmpp_jax.refine.heldout_psnr`), rendered exactly as ``llrmpp render`` does.
"""

from __future__ import annotations

import dataclasses
from typing import NamedTuple

import jax.numpy as jnp
import numpy as np

from llrmpp_jax.capture.render import frame_photos
from llrmpp_jax.capture.scene_file import SavedScene
from llrmpp_jax.errors import UserError
from llrmpp_jax.gaussians import Gaussians
from llrmpp_jax.refine import RefineConfig, RefineInfo, heldout_psnr, refine


class RefinedScene(NamedTuple):
    """A refinement's result: the scene with its new Gaussians and the scores."""

    scene: SavedScene  # the input scene with the refined Gaussians (everything else as it was)
    psnr_before: float  # held-out targets' mean PSNR (dB) before the fit
    psnr_after: float  # ... and after it
    info: RefineInfo


def refine_scene(
    saved: SavedScene,
    params: dict,
    steps: int = 10,
    rc: RefineConfig = RefineConfig(),
    scene_path: str | None = None,
    vgg_params: dict | None = None,
    progress: bool = False,
    log=print,
) -> RefinedScene:
    """Fit ``saved``'s Gaussians to its input photos for ``steps`` updates.

    ``scene_path`` overrides the capture folder recorded in ``saved``; ``log`` receives
    the "PSNR before" line as soon as it is known (the fit may take minutes). Bad input
    (no held-out targets, ``steps < 1``, ``rc.views_per_step`` above the number of inputs,
    photos that no longer match) raises ``ValueError`` with one line.
    """
    n_in = len(saved.inputs)
    if len(saved.targets) == 0:
        raise UserError("the .gs file has no held-out targets to measure the refinement on")
    if steps < 1:
        raise UserError(f"steps must be >= 1, got {steps}")
    if rc.views_per_step > n_in:
        raise UserError(f"views per step must be at most the {n_in} input views, got {rc.views_per_step}")
    cfg = saved.model
    views = {}
    for what, idx in (("inputs", saved.inputs), ("targets", saved.targets)):
        views[what] = (
            jnp.asarray(frame_photos(saved, idx, scene_path)[None]),
            jnp.asarray(saved.c2w[idx][None], jnp.float32),
            jnp.asarray(saved.intrinsics[idx][None], jnp.float32),
        )
    g = Gaussians(*(jnp.asarray(x)[None] for x in saved.gaussians))
    before = heldout_psnr(params, cfg, g, *views["targets"])
    log(f"PSNR before {before:.2f}")
    g, info = refine(params, cfg, g, *views["inputs"], steps=steps, rc=rc, vgg_params=vgg_params, progress=progress)
    after = heldout_psnr(params, cfg, g, *views["targets"])
    refined = dataclasses.replace(saved, gaussians=Gaussians(*(np.asarray(x[0]) for x in g)))  # pyright: ignore[reportArgumentType] -- a NumPy array where jax.Array is annotated: both work
    return RefinedScene(refined, before, after, info)
