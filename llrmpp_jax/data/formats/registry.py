"""One entry point for every on-disk scene format: :func:`read_scene` (``kind="auto"``
detects the format from what the path holds), :func:`dataset_scenes` (the scenes of a
dataset root) and :func:`listed_scenes` (those a split's scene list names). Used by the
CLI, the trainer and evaluation alike.

Detection, first match wins, for a path ``P``:

* ``nerfstudio``: ``P/transforms.json`` or ``P`` is such a file;
* ``colmap``: a model (``cameras.bin|txt``) in ``P/sparse/0``, ``P/sparse`` or ``P`` itself,
  images in ``P/images`` (or next to the ``sparse`` folder);
* ``scannet``: ``P/pose/`` and ``P/intrinsic/``;
* ``long_lrm``: ``P/opencv_cameras.json`` or a JSON file whose frames carry ``file_path`` +
  ``w2c``; ``re10k``: a JSON file whose frames carry ``image_path`` + ``fxfycxcy``.
"""

from __future__ import annotations

import json
import os
import typing
from collections.abc import Callable
from typing import Literal

from llrmpp_jax.data.formats.colmap import read_colmap_scene
from llrmpp_jax.data.formats.long_lrm import SCENE_JSON, read_long_lrm_index, read_long_lrm_scene
from llrmpp_jax.data.formats.nerfstudio import TRANSFORMS_JSON, read_nerfstudio_scene
from llrmpp_jax.data.formats.re10k import read_re10k_scene
from llrmpp_jax.data.formats.scannet import read_scannet_scene
from llrmpp_jax.data.scene import Scene
from llrmpp_jax.errors import MissingInputError, UserError

LOOKED_FOR = (
    f"{TRANSFORMS_JSON} (nerfstudio), sparse/0/ or sparse/ or cameras.bin|txt (COLMAP), "
    f"pose/ + intrinsic/ (ScanNet), {SCENE_JSON} or a scene .json (Long-LRM, RE10K)"
)


def colmap_model_dir(path: str) -> str | None:
    """The folder holding ``path``'s COLMAP model (``sparse/0``, ``sparse`` or ``path``), or
    None. ``ValueError`` if the model has cameras but no ``images.bin``/``images.txt``."""
    for d in (os.path.join(path, "sparse", "0"), os.path.join(path, "sparse"), path):
        if any(os.path.isfile(os.path.join(d, f"cameras{e}")) for e in (".bin", ".txt")):
            if not any(os.path.isfile(os.path.join(d, f"images{e}")) for e in (".bin", ".txt")):
                raise UserError(f"COLMAP model {d}: has cameras but no images.bin or images.txt")
            return d
    return None


def _colmap_image_dir(path: str, model_dir: str) -> str:
    """``path/images``, else ``images`` beside the ``sparse`` folder."""
    for d in (
        os.path.join(path, "images"),
        os.path.join(model_dir, "..", "..", "images"),
        os.path.join(model_dir, "..", "images"),
    ):
        if os.path.isdir(d):
            return os.path.normpath(d)
    return os.path.join(path, "images")


def _json_kind(path: str) -> str | None:
    try:
        with open(path) as f:
            data = json.load(f)
    except (OSError, ValueError):
        return None
    frames = data if isinstance(data, list) else data.get("frames") if isinstance(data, dict) else None
    first = frames[0] if isinstance(frames, list) and frames and isinstance(frames[0], dict) else {}
    if "transform_matrix" in first:
        return "nerfstudio"
    if "image_path" in first and "fxfycxcy" in first:
        return "re10k"
    if "file_path" in first and "w2c" in first:
        return "long_lrm"
    return None


def detect_format(path: str) -> str:
    """The format of the scene at ``path`` (a folder or a metadata file); ``ValueError``
    listing what was looked for when none matches."""
    if not os.path.exists(path):
        raise MissingInputError(f"scene not found: {path}")
    if os.path.isfile(path):
        kind = _json_kind(path) if path.endswith(".json") else None
    elif os.path.isfile(os.path.join(path, TRANSFORMS_JSON)):
        kind = "nerfstudio"
    elif colmap_model_dir(path) is not None:
        kind = "colmap"
    elif os.path.isdir(os.path.join(path, "pose")) and os.path.isdir(os.path.join(path, "intrinsic")):
        kind = "scannet"
    elif os.path.isfile(os.path.join(path, SCENE_JSON)):
        kind = "long_lrm"
    else:
        kind = None
    if kind is None:
        raise UserError(f"{path}: no known scene format (looked for {LOOKED_FOR})")
    return kind


def _read_colmap(path: str, **kw) -> Scene:
    model = colmap_model_dir(path)
    if model is None:
        raise UserError(f"{path}: no COLMAP model (looked for cameras.bin|txt in sparse/0/, sparse/, the folder)")
    return read_colmap_scene(model, _colmap_image_dir(path, model), **kw)


def _read_long_lrm(path: str, **kw) -> Scene:
    return read_long_lrm_scene(os.path.join(path, SCENE_JSON) if os.path.isdir(path) else path, **kw)


# Formats a dataset may be given in: READERS' keys, or "auto" (detected).
Format = Literal["auto", "nerfstudio", "colmap", "scannet", "long_lrm", "re10k"]
READERS: dict[str, Callable[..., Scene]] = {
    "nerfstudio": read_nerfstudio_scene,
    "colmap": _read_colmap,
    "scannet": read_scannet_scene,
    "long_lrm": _read_long_lrm,
    "re10k": read_re10k_scene,
}
FORMATS: tuple[str, ...] = typing.get_args(Format)


def read_scene(path: str, kind: Format = "auto", **kwargs) -> Scene:
    """Read the scene at ``path`` with the reader of ``kind`` (``"auto"``: detected).
    ``kwargs`` go to the reader (e.g. ``missing="error"``)."""
    if kind not in FORMATS:
        raise UserError(f"format must be one of {FORMATS}, got {kind!r}")
    if not os.path.exists(path):
        raise MissingInputError(f"scene not found: {path}")
    return READERS[detect_format(path) if kind == "auto" else kind](path, **kwargs)


def dataset_scenes(path: str, kind: Format = "auto") -> list[str]:
    """Scene paths of a dataset: the entries of a Long-LRM ``.txt`` index, the path itself
    when it is one scene (of format ``kind``, or any with ``"auto"``), else its sub-folders
    (sorted; each is read with :func:`read_scene`, so ``"auto"`` detects per scene)."""
    if not os.path.exists(path):
        raise MissingInputError(f"dataset path does not exist: {path}")
    if path.endswith(".txt"):
        return read_long_lrm_index(path)
    try:
        found = detect_format(path)
    except ValueError:
        found = None
    if found is not None and kind in ("auto", found):
        return [path]
    subs = (
        sorted(os.path.join(path, d) for d in os.listdir(path) if os.path.isdir(os.path.join(path, d)))
        if os.path.isdir(path)
        else []
    )
    if not subs and kind == "auto":
        raise UserError(f"dataset {path} holds no scenes (looked for {LOOKED_FOR}, in it or its sub-folders)")
    return subs or [path]


def listed_scenes(root: str, scene_list: str) -> list[str]:
    """The scenes a split's list names, as folders of ``root``, in the list's order.

    ``scene_list``: a text file of scene names, one a line (blank lines ignored), e.g.
    ScanNet's ``scannetv2_test.txt``. One-line errors: the list or ``root`` is missing, the
    list is empty, or it names scenes that are not folders of ``root`` (how many, and the
    first of them).
    """
    if not os.path.isfile(scene_list):
        raise MissingInputError(f"scene list not found: {scene_list}")
    if not os.path.isdir(root):
        raise MissingInputError(f"dataset path does not exist: {root}")
    with open(scene_list) as f:
        names = [line.strip() for line in f if line.strip()]
    if not names:
        raise UserError(f"scene list {scene_list} names no scenes")
    missing = [n for n in names if not os.path.isdir(os.path.join(root, n))]
    if missing:
        raise MissingInputError(
            f"scene list {scene_list}: {len(missing)} of its {len(names)} scenes are not "
            f"folders of {root}, the first: {missing[0]}"
        )
    return [os.path.join(root, n) for n in names]
