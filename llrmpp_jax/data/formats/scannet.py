"""ScanNetv2 frames as exported by ScanNet's ``SensReader`` (``export_sampled_data``):

``color/<i>.jpg`` (or ``.png``), ``depth/<i>.png`` (16-bit millimetres, 0 = invalid),
``pose/<i>.txt`` (4x4 camera-to-world, OpenCV axes; ``-inf`` rows where tracking failed),
``intrinsic/intrinsic_color.txt`` and ``intrinsic/intrinsic_depth.txt`` (4x4 K).

Colour and depth share the pose (identity colour-depth extrinsics in the export) but not
the intrinsics, so the reader registers depth to colour: the output frame has the colour
camera's intrinsics at the chosen resolution, colour is resized to it, and depth is
resampled (nearest) from the depth camera's pixel grid into it through ``K_c K_d^-1``.
"""

from __future__ import annotations

import os
import warnings
from typing import Literal

import numpy as np

from llrmpp_jax.data.formats.common import Missing, check_frames, present_mask, write_frames
from llrmpp_jax.data.image_io import image_size, read_depth, read_image
from llrmpp_jax.data.resample import remap, resize_image
from llrmpp_jax.data.scene import Scene
from llrmpp_jax.errors import MissingInputError, UserError
from llrmpp_jax.geometry import resize_intrinsics


def _read_matrix(path: str, what: str) -> np.ndarray:
    try:
        m = np.loadtxt(path, dtype=np.float64)
    except FileNotFoundError:
        raise MissingInputError(f"ScanNet {what} file not found: {path}") from None
    except ValueError as e:
        raise UserError(f"ScanNet {what} file {path}: not a 4x4 matrix of numbers ({e})") from None
    if m.shape != (4, 4):
        raise UserError(f"ScanNet {what} file {path}: expected a 4x4 matrix, got shape {m.shape}")
    return m


def _k_to_vec(k: np.ndarray, path: str) -> np.ndarray:
    out = np.array([k[0, 0], k[1, 1], k[0, 2], k[1, 2]])
    if not np.isfinite(out).all() or (out[:2] <= 0).any():
        raise UserError(f"ScanNet intrinsics file {path}: focal lengths must be finite and > 0, got {out.tolist()}")
    return out


def read_scannet_scene(
    scene_dir: str,
    resolution: Literal["depth", "color"] = "depth",
    frame_step: int = 1,
    missing: Missing = "skip",
) -> Scene:
    """Read an exported ScanNet scene folder into a :class:`Scene` with depth.

    Args:
      scene_dir: folder holding ``color/ depth/ pose/ intrinsic/``.
      resolution: ``"depth"`` -> frames at the depth maps' size (colour downsampled),
        ``"color"`` -> at the colour images' size (depth upsampled, nearest).
      frame_step: keep every ``frame_step``-th frame (by frame number order).
      missing: frames whose colour or depth file is absent are skipped (one counting
        warning) or raise. Frames with non-finite poses are always skipped, with a warning.
    """
    if resolution not in ("depth", "color"):
        raise UserError(f"resolution must be 'depth' or 'color', got {resolution!r}")
    pose_dir = os.path.join(scene_dir, "pose")
    if not os.path.isdir(pose_dir):
        raise MissingInputError(f"ScanNet pose folder not found: {pose_dir}")
    stems = sorted((f[:-4] for f in os.listdir(pose_dir) if f.endswith(".txt")), key=lambda s: (len(s), s))
    stems = stems[::frame_step]
    k_color_path = os.path.join(scene_dir, "intrinsic", "intrinsic_color.txt")
    k_depth_path = os.path.join(scene_dir, "intrinsic", "intrinsic_depth.txt")
    k_color = _k_to_vec(_read_matrix(k_color_path, "intrinsics"), k_color_path)
    k_depth = _k_to_vec(_read_matrix(k_depth_path, "intrinsics"), k_depth_path)

    def color_path(stem: str) -> str:
        jpg = os.path.join(scene_dir, "color", stem + ".jpg")
        return jpg if os.path.exists(jpg) else os.path.join(scene_dir, "color", stem + ".png")

    color_paths = [color_path(s) for s in stems]
    depth_paths = [os.path.join(scene_dir, "depth", s + ".png") for s in stems]
    keep = present_mask(color_paths, "color", scene_dir, missing) & present_mask(
        depth_paths, "depth", scene_dir, missing
    )
    poses = (
        np.stack([_read_matrix(os.path.join(pose_dir, s + ".txt"), "pose") for s in stems])
        if stems
        else np.zeros((0, 4, 4))
    )
    finite = np.isfinite(poses).reshape(len(stems), -1).all(axis=1)
    if not finite[keep].all():  # pyright: ignore[reportIndexIssue] -- finite is a bool array (all(axis=1))
        warnings.warn(
            f"{scene_dir}: skipped {int((~finite[keep]).sum())} frames with invalid (non-finite) poses",  # pyright: ignore[reportIndexIssue] -- as above
            stacklevel=2,
        )
    idx = np.flatnonzero(keep & finite)
    color_paths = [color_paths[i] for i in idx]
    depth_paths = [depth_paths[i] for i in idx]
    poses = poses[idx]
    if not color_paths:
        raise UserError(f"{scene_dir}: empty scene (no frame with colour, depth and a valid pose)")

    color_hw = image_size(color_paths[0])
    depth_hw = image_size(depth_paths[0])
    out_hw = depth_hw if resolution == "depth" else color_hw
    k_out = resize_intrinsics(k_color, color_hw, out_hw)
    intrinsics = np.tile(k_out[None], (len(idx), 1))
    check_frames(scene_dir, poses, intrinsics, color_paths)

    # Output pixel centre p -> depth-camera pixel: p_d = K_d K_out^-1 p (shared optical centre).
    x = np.arange(out_hw[1], dtype=np.float64) + 0.5
    y = np.arange(out_hw[0], dtype=np.float64) + 0.5
    grid = np.stack(np.meshgrid(x, y, indexing="xy"), axis=-1)
    src = (grid - k_out[2:]) / k_out[:2] * k_depth[:2] + k_depth[2:]

    def load_color(i: int) -> np.ndarray:
        img = read_image(color_paths[i])
        if img.shape[:2] != color_hw:
            raise UserError(
                f"ScanNet colour image {color_paths[i]} is {img.shape[:2]}, expected {color_hw} like the first frame"
            )
        return resize_image(img, out_hw)

    def load_depth(i: int) -> np.ndarray:
        d = read_depth(depth_paths[i], 1e-3)
        if d.shape != depth_hw:
            raise UserError(
                f"ScanNet depth map {depth_paths[i]} is {d.shape}, expected {depth_hw} like the first frame"
            )
        return remap(d, src, nearest=True)

    return Scene(
        name=os.path.basename(os.path.normpath(scene_dir)),
        c2w=poses,
        intrinsics=intrinsics,
        hw=np.tile(np.array([out_hw], dtype=np.int64), (len(idx), 1)),
        frame_names=tuple(color_paths),
        image_fn=load_color,
        depth_fn=load_depth,
    )


def write_scannet_scene(scene: Scene, out_dir: str, image_ext: str = ".png", bits: int = 16) -> str:
    """Write ``scene`` (which must have depth and one size and intrinsics for all frames) as
    a ScanNet export: colour (PNG 16-bit by default for a lossless round trip; ScanNet itself
    uses ``.jpg``), depth in millimetres, poses, and equal colour and depth intrinsics."""
    if not scene.has_depth:
        raise UserError(f"write_scannet_scene: scene {scene.name!r} has no depth maps")
    if (scene.hw != scene.hw[:1]).any() or (scene.intrinsics != scene.intrinsics[:1]).any():
        raise UserError(f"write_scannet_scene: scene {scene.name!r} must have one image size and one set of intrinsics")
    n = len(scene)
    write_frames(
        scene,
        out_dir,
        [f"color/{i}{image_ext}" for i in range(n)],
        [f"depth/{i}.png" for i in range(n)],
        bits=bits,
        depth_scale=1e-3,
    )
    os.makedirs(os.path.join(out_dir, "pose"), exist_ok=True)
    os.makedirs(os.path.join(out_dir, "intrinsic"), exist_ok=True)
    for i in range(n):
        np.savetxt(os.path.join(out_dir, "pose", f"{i}.txt"), scene.c2w[i], fmt="%.17g")
    fx, fy, cx, cy = scene.intrinsics[0]
    k = np.array([[fx, 0, cx, 0], [0, fy, cy, 0], [0, 0, 1, 0], [0, 0, 0, 1]])
    for name in ("intrinsic_color.txt", "intrinsic_depth.txt"):
        np.savetxt(os.path.join(out_dir, "intrinsic", name), k, fmt="%.17g")
    return out_dir
