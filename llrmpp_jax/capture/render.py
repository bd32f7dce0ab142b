"""Render saved Gaussians along a camera path: the held-out targets, the input views, a
smooth path through the inputs, or an orbit; optional depth and metrics; PNG, EXR and MP4.

Paths (cameras in the normalised scene frame of the :class:`~.scene_file.SavedScene`):

* ``targets`` / ``inputs`` -- the capture's own cameras (frames named after their photos);
* ``spline`` -- ``frames`` views through the input cameras in capture order: positions on
  an interpolating cubic B-spline (``scipy.interpolate.make_interp_spline``), rotations by
  ``scipy.spatial.transform.Slerp``, both over the input index;
* ``orbit`` -- ``frames`` views on a circle around the point nearest every input's optical
  axis (least squares), in the plane of the inputs' mean up, looking at that point.

Intrinsics of the synthetic paths: the mean of the inputs'. Depth is the Gaussians' expected
camera z (``sum w_i z_i / sum w_i``, 0 where nothing is hit), converted to the capture's
units by undoing the normalisation scale.
"""

from __future__ import annotations

import functools
import os
from dataclasses import dataclass

import jax
import jax.numpy as jnp
import numpy as np
from scipy.interpolate import make_interp_spline
from scipy.spatial.transform import Rotation, Slerp
from tqdm.auto import tqdm

from llrmpp_jax.array_typing import Float
from llrmpp_jax.capture.scene_file import SavedScene
from llrmpp_jax.compile_cache import announce
from llrmpp_jax.config import ModelConfig
from llrmpp_jax.errors import UserError
from llrmpp_jax.gaussian_depth import splat_depth_view
from llrmpp_jax.gaussians import Gaussians
from llrmpp_jax.model import fit_capacity, render

PATHS = ("targets", "inputs", "spline", "orbit")


def spline_at(
    c2w: Float[np.ndarray, "V 4 4"], positions: Float[np.ndarray, " frames"]
) -> Float[np.ndarray, "frames 4 4"]:
    """Poses on the spline through the ``V >= 2`` poses ``c2w`` in order, at ``positions``
    in ``[0, V - 1]`` (the integer ``i`` is pose ``i``): centres by a cubic spline, rotations
    by slerp (see the module doc)."""
    v = c2w.shape[0]
    if v < 2:
        raise UserError(f"a spline needs >= 2 input cameras, got {v}")
    t = np.arange(v, dtype=np.float64)
    out = np.tile(np.eye(4), (len(positions), 1, 1))
    out[:, :3, 3] = make_interp_spline(t, c2w[:, :3, 3], k=min(3, v - 1))(positions)
    out[:, :3, :3] = Slerp(t, Rotation.from_matrix(c2w[:, :3, :3]))(positions).as_matrix()
    return out


def spline_path(c2w: Float[np.ndarray, "V 4 4"], frames: int) -> Float[np.ndarray, "frames 4 4"]:
    """``frames`` poses through the ``V >= 2`` poses ``c2w`` in order, evenly in the spline's
    parameter (see the module doc)."""
    if c2w.shape[0] < 2 or frames < 2:
        raise UserError(f"spline path needs >= 2 input cameras and >= 2 frames, got {c2w.shape[0]} and {frames}")
    return spline_at(c2w, np.linspace(0.0, c2w.shape[0] - 1.0, frames))


def orbit_path(c2w: Float[np.ndarray, "V 4 4"], frames: int) -> Float[np.ndarray, "frames 4 4"]:
    """``frames`` poses orbiting the inputs' common look-at point (see the module doc)."""
    o, d = c2w[:, :3, 3], c2w[:, :3, 2]
    proj = np.eye(3)[None] - d[:, :, None] * d[:, None, :]  # [V, 3, 3] projections off each axis
    centre = np.linalg.lstsq(proj.sum(0), np.einsum("vij,vj->i", proj, o), rcond=None)[0]
    up = -c2w[:, :3, 1].mean(0)
    up /= np.linalg.norm(up)
    rel = o - centre
    height = float((rel @ up).mean())
    flat = rel - (rel @ up)[:, None] * up
    radius = float(np.linalg.norm(flat, axis=1).mean())
    e1 = flat[0] / max(np.linalg.norm(flat[0]), 1e-12)
    e2 = np.cross(up, e1)
    ang = np.linspace(0.0, 2 * np.pi, frames, endpoint=False)
    eye = centre + height * up + radius * (np.cos(ang)[:, None] * e1 + np.sin(ang)[:, None] * e2)
    fwd = centre - eye
    fwd /= np.linalg.norm(fwd, axis=1, keepdims=True)
    down = -up - (-up @ fwd.T)[:, None] * fwd
    down /= np.linalg.norm(down, axis=1, keepdims=True)
    out = np.tile(np.eye(4), (frames, 1, 1))
    out[:, :3, 0], out[:, :3, 1], out[:, :3, 2], out[:, :3, 3] = np.cross(down, fwd), down, fwd, eye
    return out


def path_cameras(
    saved: SavedScene, kind: str, frames: int = 60
) -> tuple[Float[np.ndarray, "frames 4 4"], Float[np.ndarray, "frames 4"], list[str], np.ndarray | None]:
    """``(c2w, intrinsics, names, frame indices or None)`` of path ``kind`` (module doc);
    names are the source photos' file stems for ``targets``/``inputs``."""
    if kind not in PATHS:
        raise UserError(f"--path must be one of {PATHS}, got {kind!r}")
    if kind in ("targets", "inputs"):
        idx = saved.targets if kind == "targets" else saved.inputs
        if len(idx) == 0:
            raise UserError(f"the scene has no {kind} to render")
        names = [os.path.splitext(os.path.basename(saved.frame_names[i]))[0] for i in idx]
        return saved.c2w[idx], saved.intrinsics[idx], names, np.asarray(idx)
    make = spline_path if kind == "spline" else orbit_path
    c2w = make(saved.c2w[saved.inputs], frames)
    k = np.broadcast_to(saved.intrinsics[saved.inputs].mean(0), (frames, 4)).copy()
    return c2w, k, [f"{kind}_{i:05d}" for i in range(frames)], None


@dataclass(frozen=True)
class RenderedViews:
    """``rgb [frames, H, W, 3]`` in [0, 1]; ``depth [frames, H, W]`` camera z in capture units (0 where
    nothing was hit) or None; ``names`` one per view."""

    rgb: Float[np.ndarray, "frames H W 3"]
    depth: Float[np.ndarray, "frames H W"] | None
    names: list[str]


@functools.partial(jax.jit, static_argnames=("cfg", "height", "width"))
def _render_rgb(params, cfg: ModelConfig, g: Gaussians, c2w, k, height: int, width: int):
    out = render(params, cfg, jax.tree.map(lambda x: x[None], g), c2w[None, None], k[None, None], height, width)
    return out.images["rgb"][0, 0]


@functools.partial(jax.jit, static_argnames=("cfg", "height", "width"))
def _render_depth(g: Gaussians, cfg: ModelConfig, c2w, k, height: int, width: int):
    return splat_depth_view(g, cfg, (c2w, k), (height, width)).depth  # 3D or 2D Gaussians, as cfg.head says


def render_views(
    params: dict,
    saved: SavedScene,
    c2w: Float[np.ndarray, "frames 4 4"],
    intrinsics: Float[np.ndarray, "frames 4"],
    names: list[str],
    *,
    depth: bool = False,
    progress: bool = True,
) -> RenderedViews:
    """Render ``saved``'s Gaussians at each camera (normalised frame, the view size of
    ``saved``), one jitted view at a time with a progress bar. The splat buffer is sized for
    the most any of these views needs (:func:`~llrmpp_jax.model.fit_capacity`), so no
    entry is dropped."""
    h, w = saved.image_hw
    g = Gaussians(*(jnp.asarray(x) for x in saved.gaussians))
    rgb, dep = [], []

    def frame(i: int, cfg: ModelConfig) -> None:
        cam = jnp.asarray(c2w[i], jnp.float32), jnp.asarray(intrinsics[i], jnp.float32)
        rgb.append(np.clip(np.asarray(_render_rgb(params, cfg, g, *cam, h, w)), 0.0, 1.0))
        if depth:
            dep.append(np.asarray(_render_depth(g, cfg, *cam, h, w)) / saved.scene_scale)

    # The buffer sizing and the first frame compile; say so, and whether the compile cache had them.
    with announce(f"the renderer for {h}x{w}{' with depth' if depth else ''}", tqdm.write if progress else None):
        cfg = fit_capacity(
            params,
            saved.model,
            jax.tree.map(lambda x: x[None], g),
            jnp.asarray(c2w, jnp.float32)[None],
            jnp.asarray(intrinsics, jnp.float32)[None],
            h,
            w,
        )
        frame(0, cfg)
    frames = tqdm(
        range(1, len(c2w)), desc="render", initial=1, total=len(c2w), disable=not progress, dynamic_ncols=True
    )
    for i in frames:
        frame(i, cfg)
    return RenderedViews(np.stack(rgb), np.stack(dep).astype(np.float32) if depth else None, list(names))


def write_video(path: str, frames: Float[np.ndarray, "frames H W 3"], fps: float) -> None:
    """H.264 MP4 (yuv420p) of ``frames`` in [0, 1] through imageio-ffmpeg."""
    import warnings

    import imageio_ffmpeg

    n, h, w, _ = frames.shape
    os.makedirs(os.path.dirname(os.path.abspath(path)), exist_ok=True)
    writer = imageio_ffmpeg.write_frames(
        path,
        (w, h),
        fps=fps,  # pyright: ignore[reportArgumentType] -- ffmpeg takes a fractional frame rate
        codec="libx264",
        pix_fmt_out="yuv420p",
        macro_block_size=2,
        quality=8,
    )
    with warnings.catch_warnings():  # the ffmpeg child exec()s at once: JAX's threads are not touched
        warnings.filterwarnings("ignore", message=r"os\.fork\(\) was called", category=RuntimeWarning)
        writer.send(None)  # starts the ffmpeg process
    for f in frames:
        writer.send(np.ascontiguousarray(np.rint(np.clip(f, 0, 1) * 255).astype(np.uint8)))
    writer.close()


def frame_photos(saved: SavedScene, frames: np.ndarray, scene_path: str | None = None) -> Float[np.ndarray, "T H W 3"]:
    """The capture's photos of ``frames``, brought to the view size exactly as the inputs
    were, re-read from ``scene_path`` (default ``saved.scene_path``); ``ValueError`` if
    its frames are not those reconstructed."""
    import warnings

    from llrmpp_jax.data.formats import read_scene
    from llrmpp_jax.data.preprocess import load_views

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # dropped frames were reported at reconstruction
        scene = read_scene(scene_path or saved.scene_path, saved.scene_format)  # pyright: ignore[reportArgumentType] -- the saved scene's format is a Format name
    base = lambda names: [os.path.basename(n) for n in names]  # noqa: E731  the folder may have moved
    if base(scene.frame_names) != base(saved.frame_names):
        raise UserError(
            f"{scene_path or saved.scene_path}: its frames ({len(scene)}) are no longer those reconstructed "
            f"({len(saved.frame_names)}); reconstruct again"
        )
    return load_views(scene, frames, saved.resized_hw, saved.crop_box, None, False)[0]


def view_metrics(
    rgb: Float[np.ndarray, "T H W 3"], photos: Float[np.ndarray, "T H W 3"], lpips_params: dict | None
) -> list[dict[str, float]]:
    """Per view ``{"psnr", "ssim"[, "lpips"]}`` of renders against photos (all views at once)."""
    from llrmpp_jax.metrics import lpips, psnr, ssim

    p, t = jnp.asarray(rgb, jnp.float32), jnp.asarray(photos, jnp.float32)
    cols = {"psnr": psnr(p, t), "ssim": ssim(p, t)}
    if lpips_params is not None:
        cols["lpips"] = lpips(lpips_params, p, t)
    return [{k: float(v[i]) for k, v in cols.items()} for i in range(rgb.shape[0])]
