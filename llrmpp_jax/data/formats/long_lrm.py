"""Long-LRM's scene format (reference facts §3.1).

A dataset is a ``.txt`` file with one scene-JSON path per line (relative paths resolve
against the txt's folder). A scene JSON is
``{"scene_name": str, "frames": [{"file_path", "w2c" (4x4 OpenCV), "h", "w", "fx", "fy",
"cx", "cy"}, ...]}`` with ``file_path`` relative to the JSON's folder (LaCT writes the bare
frame list instead; both are read). Optional keys: ``"fold_<every>_kmeans_<n>_input"``
(cached k-means input indices) and, as this project's extension, per-frame
``"depth_path"`` (float EXR in metres, or 16-bit PNG in units of ``"depth_scale"`` metres).
"""

from __future__ import annotations

import json
import os

import numpy as np

from llrmpp_jax.data.formats.common import Missing, files_scene, resolve, write_frames
from llrmpp_jax.data.scene import Scene
from llrmpp_jax.data.selection import checked_inputs
from llrmpp_jax.errors import UserError
from llrmpp_jax.file_kinds import read_json

SCENE_JSON = "opencv_cameras.json"


def _load(path: str) -> dict:
    data = read_json(path, "a Long-LRM scene file (JSON)")
    if isinstance(data, list):  # LaCT: bare list of frames
        data = {"scene_name": os.path.basename(os.path.dirname(os.path.abspath(path))), "frames": data}
    if not isinstance(data, dict) or not isinstance(data.get("frames"), list):
        raise UserError(f"{path}: expected an object with a 'frames' list")
    return data


def read_long_lrm_index(txt_path: str) -> list[str]:
    """Scene-JSON paths listed in a Long-LRM dataset ``.txt`` (blank lines ignored)."""
    with open(txt_path) as f:
        lines = [ln.strip() for ln in f]
    return [resolve(os.path.dirname(os.path.abspath(txt_path)), ln) for ln in lines if ln]


def read_long_lrm_scene(json_path: str, missing: Missing = "skip", depth_scale: float = 1e-3) -> Scene:
    """Read one Long-LRM scene JSON into a lazily loaded :class:`Scene`.

    Frames whose image file is absent are skipped with one warning (``missing="skip"``) or
    raise ``FileNotFoundError`` (``"error"``). A frame lacking a key or holding a bad value
    raises ``ValueError`` naming the file, the frame and the field.
    """
    data = _load(json_path)
    base = os.path.dirname(os.path.abspath(json_path))
    frames = data["frames"]
    c2w, intr, hw, images, depths = [], [], [], [], []
    for k, fr in enumerate(frames):
        try:
            w2c = np.asarray(fr["w2c"], dtype=np.float64)
            if w2c.shape != (4, 4):
                raise UserError(f"w2c must be 4x4, got shape {w2c.shape}")
            if not np.isfinite(w2c).all():
                raise UserError(f"w2c has {int((~np.isfinite(w2c)).sum())} non-finite value(s): {w2c.tolist()}")
            c2w.append(np.linalg.inv(w2c))
            intr.append([float(fr[key]) for key in ("fx", "fy", "cx", "cy")])
            hw.append([float(fr["h"]), float(fr["w"])])
            images.append(resolve(base, fr["file_path"]))
            if "depth_path" in fr:
                depths.append(resolve(base, fr["depth_path"]))
        except (KeyError, TypeError, ValueError, np.linalg.LinAlgError) as e:
            field = e.args[0] if isinstance(e, KeyError) else "w2c/intrinsics"
            raise UserError(f"{json_path}, frame {k}: bad or missing field {field!r}: {e}") from None
    if depths and len(depths) != len(images):
        raise UserError(
            f"{json_path}: 'depth_path' is given for {len(depths)} of {len(images)} frames; expected all or none"
        )
    return files_scene(
        name=str(data.get("scene_name", os.path.basename(base))),
        source=json_path,
        image_paths=images,
        c2w=np.asarray(c2w).reshape(-1, 4, 4),
        intrinsics=np.asarray(intr).reshape(-1, 4),
        declared_hw=np.asarray(hw).reshape(-1, 2),
        depth_paths=depths or None,
        depth_scale=float(data.get("depth_scale", depth_scale)),
        missing=missing,
    )


def cached_kmeans_inputs(json_path: str, every: int, num_inputs: int, num_frames: int) -> np.ndarray | None:
    """The ``fold_<every>_kmeans_<num_inputs>_input`` indices cached in a scene JSON, sorted
    int64, or None if the JSON has none. ``num_frames``: frames of the scene as read.

    Raises:
      ValueError (one line): the indices are not ``num_inputs`` integers in ``[0,
        num_frames)``, or the reader skipped frames (missing images), so they no longer
        index the scene.
    """
    data = _load(json_path)
    key = f"fold_{every}_kmeans_{num_inputs}_input"
    if key not in data:
        return None
    if len(data["frames"]) != num_frames:
        raise UserError(
            f"{json_path}: '{key}' indexes the JSON's {len(data['frames'])} frames but {num_frames} were read "
            f"(frames without images are skipped); restore the images or delete the key to recompute it"
        )
    return checked_inputs(data[key], num_frames, num_inputs, f"{json_path}: '{key}'")


def read_kmeans_index(path: str) -> dict[str, dict]:
    """Long-LRM's file of precomputed evaluation inputs (``data/dl3dv_fold_8_kmeans_input_idx.json``:
    a list of ``{"scene_name", "fold_8_kmeans_<n>_input": [...]}``) keyed by scene name."""
    entries = read_json(path, "a k-means index file (JSON)")
    if not isinstance(entries, list) or not all(isinstance(e, dict) and "scene_name" in e for e in entries):
        raise UserError(f"{path}: expected a list of objects with a 'scene_name' (Long-LRM's k-means index)")
    return {e["scene_name"]: e for e in entries}


def write_long_lrm_scene(
    scene: Scene,
    out_dir: str,
    image_ext: str = ".png",
    bits: int = 16,
    depth_ext: str | None = ".exr",
    depth_scale: float = 1e-3,
) -> str:
    """Write ``scene`` as ``out_dir/opencv_cameras.json`` + ``images/`` (+ ``depth/`` when the
    scene has depth and ``depth_ext`` is set). Returns the JSON path."""
    n = len(scene)
    image_names = [f"images/{i:05d}{image_ext}" for i in range(n)]
    depth_names = [f"depth/{i:05d}{depth_ext}" for i in range(n)] if scene.has_depth and depth_ext else None
    write_frames(scene, out_dir, image_names, depth_names, bits=bits, depth_scale=depth_scale)
    frames = []
    for i in range(n):
        fx, fy, cx, cy = scene.intrinsics[i].tolist()
        h, w = scene.hw[i].tolist()
        frame = {
            "file_path": image_names[i],
            "w2c": np.linalg.inv(scene.c2w[i]).tolist(),
            "h": h,
            "w": w,
            "fx": fx,
            "fy": fy,
            "cx": cx,
            "cy": cy,
        }
        if depth_names is not None:
            frame["depth_path"] = depth_names[i]
        frames.append(frame)
    data = {"scene_name": scene.name, "frames": frames}
    if depth_names is not None and not depth_ext.lower().endswith(".exr"):  # pyright: ignore[reportOptionalMemberAccess] -- depth_names is None when depth_ext is
        data["depth_scale"] = depth_scale
    path = os.path.join(out_dir, SCENE_JSON)
    with open(path, "w") as f:
        json.dump(data, f, indent=1)
    return path


def write_long_lrm_index(txt_path: str, json_paths: list[str]) -> None:
    """Write a dataset ``.txt`` listing scene JSONs relative to the txt's folder."""
    base = os.path.dirname(os.path.abspath(txt_path))
    with open(txt_path, "w") as f:
        f.writelines(os.path.relpath(os.path.abspath(p), base) + "\n" for p in json_paths)
