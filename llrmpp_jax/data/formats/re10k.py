"""RealEstate10K as converted by LVSM's ``process_data.py`` into one JSON per scene:
``{"scene_name", "frames": [{"image_path", "fxfycxcy", "w2c" (4x4 OpenCV)}]}``.

pixelSplat's ``.torch`` chunks store intrinsics normalised by the image width / height;
LVSM's converter multiplies them back to pixels. Both appear in the wild, so the reader
takes ``intrinsics_units="auto"``: normalised when every ``cx`` and ``cy`` is below 1
(a principal point inside the first pixel is not a real camera), pixels otherwise.
``image_path`` is absolute (LVSM) or relative to the JSON's folder. The evaluation split
file (``evaluation_index_re10k.json``: scene -> context and target frame indices) is read by
:func:`read_re10k_eval_index`.
"""

from __future__ import annotations

import json
import os
from typing import Literal

import numpy as np

from llrmpp_jax.data.formats.common import Missing, files_scene, resolve, write_frames
from llrmpp_jax.data.image_io import image_size
from llrmpp_jax.data.scene import Scene
from llrmpp_jax.errors import UserError
from llrmpp_jax.file_kinds import read_json

Units = Literal["auto", "pixels", "normalized"]


def read_re10k_scene(json_path: str, intrinsics_units: Units = "auto", missing: Missing = "skip") -> Scene:
    """Read one converted RE10K scene JSON into a :class:`Scene`."""
    data = read_json(json_path, "an RE10K scene file (JSON)")
    base = os.path.dirname(os.path.abspath(json_path))
    frames = data.get("frames") if isinstance(data, dict) else None
    if not isinstance(frames, list):
        raise UserError(f"{json_path}: expected an object with a 'frames' list")
    c2w, intr, images = [], [], []
    for k, fr in enumerate(frames):
        try:
            w2c = np.asarray(fr["w2c"], dtype=np.float64)
            if w2c.shape == (3, 4):
                w2c = np.concatenate([w2c, [[0.0, 0.0, 0.0, 1.0]]], axis=0)
            if w2c.shape != (4, 4) or not np.isfinite(w2c).all():
                raise UserError(f"w2c must be a finite 4x4 (or 3x4) matrix, got {w2c.tolist()}")
            c2w.append(np.linalg.inv(w2c))
            k4 = [float(v) for v in fr["fxfycxcy"]]
            if len(k4) != 4:
                raise UserError(f"fxfycxcy must have 4 values, got {len(k4)}")
            intr.append(k4)
            images.append(resolve(base, str(fr["image_path"])))
        except (KeyError, TypeError, ValueError, np.linalg.LinAlgError) as e:
            field = e.args[0] if isinstance(e, KeyError) else "w2c/fxfycxcy"
            raise UserError(f"{json_path}, frame {k}: bad or missing field {field!r}: {e}") from None
    intr = np.asarray(intr, dtype=np.float64).reshape(-1, 4)
    if intrinsics_units not in ("auto", "pixels", "normalized"):
        raise UserError(f"intrinsics_units must be 'auto', 'pixels' or 'normalized', got {intrinsics_units!r}")
    normalized = intrinsics_units == "normalized" or (
        intrinsics_units == "auto" and len(intr) > 0 and bool((intr[:, 2:] < 1.0).all())
    )
    declared = None
    if normalized:
        # Scale by each image's own size, read from its header (missing files keep size 1
        # here and are dropped by files_scene).
        hw = np.array([image_size(p) if os.path.exists(p) else (1, 1) for p in images], dtype=np.float64).reshape(-1, 2)
        intr = intr * np.stack([hw[:, 1], hw[:, 0], hw[:, 1], hw[:, 0]], axis=1)
        declared = hw
    return files_scene(
        name=str(data.get("scene_name", os.path.splitext(os.path.basename(json_path))[0])),
        source=json_path,
        image_paths=images,
        c2w=np.asarray(c2w).reshape(-1, 4, 4),
        intrinsics=intr,
        declared_hw=declared,
        missing=missing,
    )


def read_re10k_eval_index(path: str) -> dict[str, tuple[list[int], list[int]]]:
    """``{scene_name: (context_indices, target_indices)}`` from an evaluation index JSON
    (scenes mapped to ``null`` are left out, as pixelSplat does)."""
    with open(path) as f:
        data = json.load(f)
    return {k: (list(v["context"]), list(v["target"])) for k, v in data.items() if v is not None}


def write_re10k_scene(
    scene: Scene, out_dir: str, normalized: bool = False, image_ext: str = ".png", bits: int = 16
) -> str:
    """Write ``scene`` as ``out_dir/<scene_name>.json`` + ``images/`` in LVSM's layout
    (intrinsics in pixels, or normalised by width/height with ``normalized``). RE10K holds
    no depth maps. Returns the JSON path."""
    n = len(scene)
    names = [f"images/{i:05d}{image_ext}" for i in range(n)]
    write_frames(scene, out_dir, names, None, bits=bits)
    frames = []
    for i in range(n):
        k = scene.intrinsics[i].copy()
        if normalized:
            h, w = scene.hw[i]
            k = k / np.array([w, h, w, h], dtype=np.float64)
        frames.append({"image_path": names[i], "fxfycxcy": k.tolist(), "w2c": np.linalg.inv(scene.c2w[i]).tolist()})
    path = os.path.join(out_dir, f"{scene.name}.json")
    with open(path, "w") as f:
        json.dump({"scene_name": scene.name, "frames": frames}, f, indent=1)
    return path
