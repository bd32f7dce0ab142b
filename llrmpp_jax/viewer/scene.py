"""What the viewer shows: one scene's Gaussians plus the input cameras that made them.

* :class:`ViewerScene` -- Gaussians (batch 1) + input cameras, their image size and
  optional thumbnails, in the scene's normalised frame.
* :func:`check_gaussians` -- a scene's Gaussians against the model config (one line).
* :func:`saved_view_scene` -- a ``.gs`` scene file's content (:class:`~llrmpp_jax.capture.SavedScene`).
* :func:`procedural_view_scene` -- reconstruct a procedural scene with a model (a scene
  source that needs no files: tests, benchmarks, ``llrmpp view --procedural SEED``).
* :func:`gaussian_centres` -- the Gaussians' centres with a colour each, for the point cloud.
"""

from __future__ import annotations

import os
from typing import NamedTuple

import jax
import numpy as np

from llrmpp_jax.array_typing import Float
from llrmpp_jax.capture.scene_file import SavedScene
from llrmpp_jax.config import ModelConfig
from llrmpp_jax.data import ProceduralConfig, ViewGeometry, make_sample, procedural_scene, uniform_inputs
from llrmpp_jax.errors import UserError
from llrmpp_jax.gaussians import Gaussians
from llrmpp_jax.model import reconstruct
from llrmpp_jax.splat.sh import SH_C0, num_sh_bases


class ViewerScene(NamedTuple):
    """A reconstructed scene as the viewer needs it (scene units, OpenCV cameras)."""

    name: str
    gaussians: Gaussians  # batch axis of size 1
    input_c2w: Float[np.ndarray, "V 4 4"]
    input_intrinsics: Float[np.ndarray, "V 4"]  # pixels of an input_hw image
    input_hw: tuple[int, int]
    thumbnails: np.ndarray | None  # uint8 [V, h, w, 3] or None


def check_gaussians(cfg: ModelConfig, gaussians: Gaussians, source: str) -> None:
    """``ValueError`` (one line naming ``source``) if ``gaussians`` cannot be rendered by a
    model of config ``cfg``: batch other than 1, inconsistent N, or a feature width that is
    not the config's F (feature mode) / ``(deg+1)^2 * 3`` SH coefficients (colour mode)."""
    shapes = {k: tuple(v.shape) for k, v in gaussians._asdict().items()}
    b, n = shapes["means"][:2]
    want = {"means": (1, n, 3), "quats": (1, n, 4), "scales": (1, n, 3), "opacities": (1, n)}
    for name, shape in want.items():
        if shapes[name] != shape:
            raise UserError(
                f"{source}: Gaussian field {name!r} has shape {shapes[name]}, expected {shape} "
                f"(one scene of N={n} Gaussians)"
            )
    f = shapes["features"]
    if cfg.head.mode == "feature":
        want_f, what = cfg.head.feature_dim, f"F={cfg.head.feature_dim} features (feature mode)"
    else:
        want_f = 3 * num_sh_bases(cfg.head.sh_degree)
        what = f"{want_f} SH coefficients of degree {cfg.head.sh_degree} (colour mode)"
    if f != (1, n, want_f):
        raise UserError(
            f"{source}: Gaussians carry {f[-1]} values per Gaussian but the model config expects "
            f"{what}; the scene was made with another model"
        )


def _uint8(images: Float[np.ndarray, "V H W 3"]) -> np.ndarray:
    return np.round(np.clip(images, 0.0, 1.0) * 255.0).astype(np.uint8)


def saved_view_scene(saved: SavedScene, input_images: Float[np.ndarray, "V H W 3"] | None = None) -> ViewerScene:
    """The viewer's scene from a ``.gs`` file's content; ``input_images`` (the inputs as fed
    to the model, in [0, 1]) become the frustums' thumbnails."""
    return ViewerScene(
        name=os.path.basename(saved.scene_path.rstrip("/")) or "scene",
        gaussians=Gaussians(*(np.asarray(a)[None] for a in saved.gaussians)),  # pyright: ignore[reportArgumentType] -- a NumPy array where jax.Array is annotated: both work
        input_c2w=np.asarray(saved.c2w[saved.inputs], np.float32),
        input_intrinsics=np.asarray(saved.intrinsics[saved.inputs], np.float32),
        input_hw=tuple(saved.image_hw),  # pyright: ignore[reportArgumentType] -- an image's two sides
        thumbnails=None if input_images is None else _uint8(input_images),
    )


def procedural_view_scene(
    params: dict, cfg: ModelConfig, seed: int, num_inputs: int = 4, size: int = 64, num_frames: int = 16
) -> ViewerScene:
    """Reconstruct procedural scene ``seed`` (``size x size``, ``num_frames`` frames) from
    ``num_inputs`` evenly spread frames with the model ``(params, cfg)``."""
    if size % cfg.size_multiple:
        raise UserError(f"procedural scene size {size} must be a multiple of {cfg.size_multiple}")
    scene = procedural_scene(seed, ProceduralConfig(height=size, width=size, num_frames=num_frames))
    inputs = uniform_inputs(num_frames, num_inputs)
    sample = make_sample(scene, inputs, inputs[:1], ViewGeometry(resize_h=size, multiple=cfg.size_multiple))
    images, c2w, intrinsics = (sample[k] for k in ("input_images", "input_c2w", "input_intrinsics"))
    gaussians = jax.jit(reconstruct, static_argnums=1)(params, cfg, images[None], c2w[None], intrinsics[None])
    return ViewerScene(scene.name, gaussians, c2w, intrinsics, (size, size), _uint8(images))


def gaussian_centres(
    cfg: ModelConfig, gaussians: Gaussians, max_points: int, rng: np.random.Generator
) -> tuple[Float[np.ndarray, "pts 3"], np.ndarray]:
    """At most ``max_points`` Gaussian centres (a random subset if there are more) and a
    ``uint8 [pts, 3]`` colour each: the SH DC colour in colour mode; in feature mode the
    features' first three principal components, each stretched to [0, 255] (features have
    no colour of their own; similar features get similar colours)."""
    means = np.asarray(gaussians.means[0], np.float32)
    feats = np.asarray(gaussians.features[0], np.float64)
    keep = np.sort(rng.choice(len(means), max_points, replace=False)) if len(means) > max_points else slice(None)
    means, feats = means[keep], feats[keep]
    if cfg.head.mode == "color":
        rgb = np.clip(0.5 + SH_C0 * feats[:, :3], 0.0, 1.0)
    else:
        centred = feats - feats.mean(axis=0)
        _, _, vt = np.linalg.svd(centred, full_matrices=False)
        pcs = centred @ vt[:3].T
        pcs = np.pad(pcs, ((0, 0), (0, 3 - pcs.shape[1])))  # F < 3 or a single point
        lo, hi = pcs.min(axis=0), pcs.max(axis=0)
        rgb = (pcs - lo) / np.maximum(hi - lo, 1e-12)
    return means, np.round(rgb * 255.0).astype(np.uint8)
