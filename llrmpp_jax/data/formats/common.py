"""Assembling a :class:`~llrmpp_jax.data.scene.Scene` from per-frame files, shared by
every reader: missing files, image sizes, intrinsics declared for another size, and
error messages that name the file and field."""

from __future__ import annotations

import os
import warnings
from collections.abc import Sequence
from typing import Literal

import numpy as np

from llrmpp_jax.data.image_io import image_size, read_depth, read_image, write_depth, write_image
from llrmpp_jax.data.scene import Scene
from llrmpp_jax.errors import MissingInputError, UserError
from llrmpp_jax.geometry import validate_cameras

Missing = Literal["skip", "error"]


def resolve(base_dir: str, path: str) -> str:
    """``path`` if absolute, else relative to ``base_dir``."""
    return path if os.path.isabs(path) else os.path.normpath(os.path.join(base_dir, path))


def present_mask(paths: Sequence[str], what: str, source: str, missing: Missing) -> np.ndarray:
    """Which files exist. Missing ones raise (``missing="error"``) or are dropped with one
    warning that counts them (``missing="skip"``)."""
    keep = np.array([os.path.exists(p) for p in paths], dtype=bool)
    if not keep.all():
        absent = [p for p, k in zip(paths, keep) if not k]
        if missing == "error":
            raise MissingInputError(f"{source}: {len(absent)} {what} file(s) not found, first: {absent[0]}")
        names = ", ".join(os.path.basename(p) for p in absent[:10]) + (" ..." if len(absent) > 10 else "")
        warnings.warn(
            f"{source}: skipped {len(absent)} of {len(paths)} frames whose {what} file is missing ({names})",
            stacklevel=3,
        )
    return keep


def check_frames(source: str, c2w: np.ndarray, intrinsics: np.ndarray, frame_names: Sequence[str]) -> None:
    """``validate_cameras`` with the source file in the message (before any image is read)."""
    if len(frame_names) == 0:
        raise UserError(f"{source}: empty scene (no frames with an image on disk)")
    validate_cameras(c2w, intrinsics, name=source, frame_names=frame_names)


def files_scene(
    name: str,
    source: str,
    image_paths: Sequence[str],
    c2w: np.ndarray,
    intrinsics: np.ndarray,
    declared_hw: np.ndarray | None = None,
    depth_paths: Sequence[str] | None = None,
    depth_scale: float = 1e-3,
    distortion: np.ndarray | None = None,
    missing: Missing = "skip",
) -> Scene:
    """A lazily loaded scene over image (and depth) files.

    Args:
      name: scene name. source: the metadata file, quoted in errors and warnings.
      image_paths: N absolute image paths. c2w ``[N, 4, 4]`` OpenCV; intrinsics ``[N, 4]`` px.
      declared_hw: ``[N, 2]`` size the intrinsics refer to, or None (= the files' size).
        When a file's real size differs (e.g. a downscaled ``images_4/`` folder) with the
        same aspect ratio, its intrinsics are rescaled exactly; otherwise ``ValueError``.
      depth_paths: N depth files or None; frames whose depth file is missing are dropped
        like missing images. distortion: ``[N, 5]`` OpenCV coefficients or None.
    """
    n = len(image_paths)
    c2w = np.asarray(c2w, dtype=np.float64).reshape(n, 4, 4)
    intrinsics = np.asarray(intrinsics, dtype=np.float64).reshape(n, 4)
    keep = present_mask(image_paths, "image", source, missing)
    if depth_paths is not None:
        keep &= present_mask(depth_paths, "depth", source, missing)
    idx = np.flatnonzero(keep)
    image_paths = [image_paths[i] for i in idx]  # pyright: ignore[reportArgumentType, reportCallIssue] -- NumPy integers index a list (they have __index__)
    depth_paths = None if depth_paths is None else [depth_paths[i] for i in idx]  # pyright: ignore[reportArgumentType, reportCallIssue] -- NumPy integers index a list (they have __index__)
    c2w, intrinsics = c2w[idx], intrinsics[idx]
    check_frames(source, c2w, intrinsics, image_paths)
    hw = np.array([image_size(p) for p in image_paths], dtype=np.int64).reshape(-1, 2)
    if declared_hw is not None:
        declared = np.asarray(declared_hw, dtype=np.float64).reshape(n, 2)[idx]
        sy, sx = hw[:, 0] / declared[:, 0], hw[:, 1] / declared[:, 1]
        bad = np.abs(sx / sy - 1.0) > 0.01
        if bad.any():
            i = int(np.argmax(bad))
            raise UserError(
                f"{source}: image {image_paths[i]} is {hw[i, 1]}x{hw[i, 0]} (WxH) but its intrinsics are "
                f"declared for {declared[i, 1]:g}x{declared[i, 0]:g}; the aspect ratios differ"
            )
        intrinsics = intrinsics * np.stack([sx, sy, sx, sy], axis=1)
    return Scene(
        name=name,
        c2w=c2w,
        intrinsics=intrinsics,
        hw=hw,
        frame_names=tuple(image_paths),
        image_fn=lambda i: read_image(image_paths[i]),
        depth_fn=None if depth_paths is None else (lambda i: read_depth(depth_paths[i], depth_scale)),
        distortion=None if distortion is None else np.asarray(distortion, dtype=np.float64).reshape(n, 5)[idx],
    )


def write_frames(
    scene: Scene,
    out_dir: str,
    image_names: Sequence[str],
    depth_names: Sequence[str] | None,
    bits: int = 16,
    depth_scale: float = 1e-3,
) -> None:
    """Write every frame's pinhole image (and depth) under ``out_dir`` at the given relative
    names. PNG takes ``bits`` 8 or 16, JPEG 8, EXR is float (lossless); depth goes to EXR as
    float metres or to PNG as 16-bit multiples of ``depth_scale``."""
    for i in range(len(scene)):
        name = image_names[i].lower()
        write_image(
            os.path.join(out_dir, image_names[i]),
            scene.image(i),
            bits=32 if name.endswith(".exr") else 8 if name.endswith((".jpg", ".jpeg")) else bits,
        )
        if depth_names is not None:
            path = os.path.join(out_dir, depth_names[i])
            write_depth(path, scene.depth(i), scale=None if path.lower().endswith(".exr") else depth_scale)
