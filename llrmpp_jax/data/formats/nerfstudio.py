"""nerfstudio / instant-ngp ``transforms.json`` (DL3DV's raw format, the fox capture).

Intrinsics ``fl_x, fl_y, cx, cy, w, h`` and OpenCV distortion ``k1, k2, k3, p1, p2`` sit at
the top level and may be overridden per frame; ``camera_angle_x`` / ``_y`` stand in for a
missing focal length (instant-ngp); a missing principal point is the image centre.
``transform_matrix`` is camera-to-world with OpenGL camera axes; it is turned into OpenCV
axes. ``dl3dv_world_remap`` also applies Long-LRM's DL3DV world-axis change
(``prosess_dl3dv.py``: swap world x and y, then negate world z). Lens distortion is removed
when images are loaded (see :class:`~llrmpp_jax.data.scene.Scene`). Optional per-frame
``depth_file_path``: 16-bit PNG in units of ``depth_unit_scale_factor`` (default 1e-3 m,
nerfstudio's default) or float EXR in metres.
"""

from __future__ import annotations

import json
import math
import os

import numpy as np

from llrmpp_jax.data.formats.common import Missing, files_scene, resolve, write_frames
from llrmpp_jax.data.image_io import image_size
from llrmpp_jax.data.scene import Scene
from llrmpp_jax.errors import UserError
from llrmpp_jax.file_kinds import read_json
from llrmpp_jax.geometry import opencv_to_opengl, opengl_to_opencv

TRANSFORMS_JSON = "transforms.json"
_PINHOLE_MODELS = ("OPENCV", "PINHOLE", "SIMPLE_PINHOLE")
# Long-LRM DL3DV remap on world coordinates: rows [1, 0, 2] then negate row 2.
_DL3DV_WORLD = np.array([[0.0, 1.0, 0.0, 0.0], [1.0, 0.0, 0.0, 0.0], [0.0, 0.0, -1.0, 0.0], [0.0, 0.0, 0.0, 1.0]])


def _frame_value(frame: dict, top: dict, key: str) -> float | None:
    value = frame.get(key, top.get(key))
    return None if value is None else float(value)


def read_nerfstudio_scene(
    path: str,
    dl3dv_world_remap: bool = False,
    undistort: bool = True,
    missing: Missing = "skip",
    image_dir: str | None = None,
) -> Scene:
    """Read a ``transforms.json`` (or the folder holding it) into a :class:`Scene`.

    Args:
      path: the JSON file or its folder.
      dl3dv_world_remap: apply Long-LRM's DL3DV world-axis remap after OpenGL -> OpenCV.
      undistort: remove ``k1, k2, k3, p1, p2`` distortion when loading (else ignore it).
      missing: frames whose image is absent are skipped with one counting warning
        (``"skip"``, instant-ngp's behaviour) or raise ``FileNotFoundError``.
      image_dir: replace the first folder of every ``file_path`` (e.g. ``"images_4"`` for
        DL3DV's 4x downscaled frames); intrinsics are rescaled to the real image size.
    """
    json_path = os.path.join(path, TRANSFORMS_JSON) if os.path.isdir(path) else path
    top = read_json(json_path, "a nerfstudio transforms file (JSON)")
    if not isinstance(top, dict):
        raise UserError(f"{json_path}: expected a JSON object with a 'frames' list, got {type(top).__name__}")
    base = os.path.dirname(os.path.abspath(json_path))
    model = str(top.get("camera_model", "OPENCV")).upper()
    if model not in _PINHOLE_MODELS:
        raise UserError(f"{json_path}: camera_model {model!r} is not supported (expected one of {_PINHOLE_MODELS})")
    frames = top.get("frames")
    if not isinstance(frames, list):
        raise UserError(f"{json_path}: missing 'frames' list")

    c2w, intr, hw, dist, images, depths = [], [], [], [], [], []
    for k, fr in enumerate(frames):
        try:
            rel = str(fr["file_path"])
            if image_dir is not None:
                rel = rel.replace("\\", "/")
                rel = os.path.join(image_dir, (rel[2:] if rel.startswith("./") else rel).split("/", 1)[-1])
            img = resolve(base, rel)
            if not os.path.splitext(img)[1] and os.path.exists(img + ".png"):  # NeRF-synthetic style
                img += ".png"
            images.append(img)
            m = np.asarray(fr["transform_matrix"], dtype=np.float64)
            if m.shape == (3, 4):
                m = np.concatenate([m, [[0.0, 0.0, 0.0, 1.0]]], axis=0)
            if m.shape != (4, 4):
                raise UserError(f"transform_matrix must be 4x4, got shape {m.shape}")
            c2w.append(m)
            w, h = _frame_value(fr, top, "w"), _frame_value(fr, top, "h")
            if w is None or h is None:
                h, w = image_size(img) if os.path.exists(img) else (1.0, 1.0)
            fx, fy = _frame_value(fr, top, "fl_x"), _frame_value(fr, top, "fl_y")
            if fx is None and "camera_angle_x" in top:
                fx = 0.5 * w / math.tan(0.5 * float(top["camera_angle_x"]))
            if fy is None:
                fy = 0.5 * h / math.tan(0.5 * float(top["camera_angle_y"])) if "camera_angle_y" in top else fx
            if fx is None or fy is None:
                raise KeyError("fl_x")
            cx, cy = _frame_value(fr, top, "cx"), _frame_value(fr, top, "cy")
            intr.append([fx, fy, w / 2 if cx is None else cx, h / 2 if cy is None else cy])
            hw.append([h, w])
            dist.append([_frame_value(fr, top, key) or 0.0 for key in ("k1", "k2", "p1", "p2", "k3")])
            if "depth_file_path" in fr:
                depths.append(resolve(base, str(fr["depth_file_path"])))
        except (KeyError, TypeError, ValueError) as e:
            field = e.args[0] if isinstance(e, KeyError) else "transform_matrix/intrinsics"
            raise UserError(f"{json_path}, frame {k}: bad or missing field {field!r}: {e}") from None
    if depths and len(depths) != len(images):
        raise UserError(f"{json_path}: 'depth_file_path' is given for {len(depths)} of {len(images)} frames")

    c2w = np.asarray(c2w).reshape(-1, 4, 4)
    if not np.isfinite(c2w).all():
        k = int(np.argmax(~np.isfinite(c2w).reshape(len(c2w), -1).all(axis=1)))
        bad = ~np.isfinite(c2w).reshape(len(c2w), -1)
        raise UserError(
            f"{json_path}, frame {k} ({images[k]}): transform_matrix has non-finite values "
            f"({int(bad.sum())} non-finite value(s) in {int(bad.any(axis=1).sum())} of {len(c2w)} frames)"
        )
    c2w = opengl_to_opencv(c2w)
    if dl3dv_world_remap:
        c2w = _DL3DV_WORLD[None] @ c2w
    distortion = np.asarray(dist).reshape(-1, 5)
    return files_scene(
        name=os.path.basename(base),
        source=json_path,
        image_paths=images,
        c2w=c2w,  # pyright: ignore[reportArgumentType] -- an np.asarray result
        intrinsics=np.asarray(intr).reshape(-1, 4),
        declared_hw=np.asarray(hw).reshape(-1, 2),
        depth_paths=depths or None,
        depth_scale=float(top.get("depth_unit_scale_factor", 1e-3)),
        distortion=distortion if undistort and distortion.any() else None,
        missing=missing,
    )


def write_nerfstudio_scene(
    scene: Scene,
    out_dir: str,
    image_ext: str = ".png",
    bits: int = 16,
    depth_ext: str | None = ".exr",
    depth_scale: float = 1e-3,
) -> str:
    """Write ``scene`` as ``out_dir/transforms.json`` (per-frame pinhole intrinsics, OpenGL
    ``transform_matrix``) + ``images/`` (+ ``depth/``). Returns the JSON path."""
    n = len(scene)
    image_names = [f"images/frame_{i:05d}{image_ext}" for i in range(n)]
    depth_names = [f"depth/frame_{i:05d}{depth_ext}" for i in range(n)] if scene.has_depth and depth_ext else None
    write_frames(scene, out_dir, image_names, depth_names, bits=bits, depth_scale=depth_scale)
    gl = opencv_to_opengl(scene.c2w)
    frames = []
    for i in range(n):
        fx, fy, cx, cy = scene.intrinsics[i].tolist()
        h, w = scene.hw[i].tolist()
        frame = {
            "file_path": image_names[i],
            "transform_matrix": gl[i].tolist(),
            "fl_x": fx,
            "fl_y": fy,
            "cx": cx,
            "cy": cy,
            "w": w,
            "h": h,
        }
        if depth_names is not None:
            frame["depth_file_path"] = depth_names[i]
        frames.append(frame)
    data = {"camera_model": "OPENCV", "frames": frames}
    if depth_names is not None:
        data["depth_unit_scale_factor"] = depth_scale
    path = os.path.join(out_dir, TRANSFORMS_JSON)
    with open(path, "w") as f:
        json.dump(data, f, indent=1)
    return path
