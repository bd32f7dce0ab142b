"""The ``.gs`` scene file: reconstructed Gaussians plus everything needed to render them
again, compare them with the photos, or put them back in the capture's world frame.

Layout: an uncompressed NumPy ``.npz`` archive. ``header`` holds UTF-8 JSON with
``format = "llrmpp-gaussians"``, ``version`` (:data:`GS_VERSION`; another version is
refused), the model config, the scene's path and format, the frame names, the input and
target frame lists and the view size and crop; the arrays are the Gaussians (one scene, no batch
axis: ``means [N, 3]``, ``quats [N, 4]`` wxyz, ``scales [N, 3]`` linear (``[N, 2]`` for a 2D
Gaussian model), ``opacities [N]``, ``features [N, F]``), the cameras of every frame in the normalised scene frame
(``c2w [M, 4, 4]`` OpenCV, ``intrinsics [M, 4]`` pixels at the view size) and
``world_from_scene [4, 4]``: the similarity taking normalised-scene points back to the
capture's world (its scale ``1 / s`` turns scene units back into capture units).
"""

from __future__ import annotations

import dataclasses
import json
import zipfile
from dataclasses import dataclass

import numpy as np

from llrmpp_jax.array_typing import Float, Int
from llrmpp_jax.config import ModelConfig, from_dict
from llrmpp_jax.errors import UserError
from llrmpp_jax.file_kinds import check_npz
from llrmpp_jax.finite import check_finite
from llrmpp_jax.gaussians import Gaussians

GS_FORMAT = "llrmpp-gaussians"
GS_VERSION = 1
_ARRAYS = (
    "means",
    "quats",
    "scales",
    "opacities",
    "features",
    "c2w",
    "intrinsics",
    "world_from_scene",
    "inputs",
    "targets",
)


@dataclass(frozen=True)
class SavedScene:
    """One reconstructed capture (what a ``.gs`` file holds).

    ``gaussians`` has no batch axis (``means [N, 3]`` ...). ``c2w`` / ``intrinsics`` cover
    every frame of the scene in the normalised frame; ``inputs`` / ``targets`` index them.
    ``image_hw`` is the view size the intrinsics refer to; ``resized_hw`` and ``crop_box``
    say how the photos were brought to it (:func:`~llrmpp_jax.data.preprocess.load_views`).
    """

    gaussians: Gaussians
    model: ModelConfig
    c2w: Float[np.ndarray, "frames 4 4"]
    intrinsics: Float[np.ndarray, "frames 4"]
    world_from_scene: Float[np.ndarray, "4 4"]
    frame_names: tuple[str, ...]
    inputs: Int[np.ndarray, " V"]
    targets: Int[np.ndarray, " T"]
    image_hw: tuple[int, int]
    resized_hw: tuple[int, int]  # frames were resized to this, then cropped to crop_box, then
    crop_box: tuple[int, int, int, int]  # (top, left, height, width) resized to image_hw
    scene_path: str
    scene_format: str

    def __post_init__(self) -> None:
        got, want = self.gaussians.scales.shape[-1], self.model.head.num_scales
        if got != want:
            raise UserError(
                f"scales have {got} axes per Gaussian but the model config's head.primitive="
                f"{self.model.head.primitive!r} has {want}"
            )

    @property
    def scene_scale(self) -> float:
        """Normalised units per capture unit (the normalisation's ``s``)."""
        return float(1.0 / np.cbrt(np.linalg.det(self.world_from_scene[:3, :3])))


def save_gs(path: str, scene: SavedScene) -> None:
    """Write ``scene`` to ``path`` (a ``.gs`` file, see the module doc)."""
    header = {
        "format": GS_FORMAT,
        "version": GS_VERSION,
        "model": dataclasses.asdict(scene.model),
        "frame_names": list(scene.frame_names),
        "image_hw": list(scene.image_hw),
        "resized_hw": list(scene.resized_hw),
        "crop_box": list(scene.crop_box),
        "scene_path": scene.scene_path,
        "scene_format": scene.scene_format,
    }
    g = scene.gaussians
    arrays = {name: np.asarray(getattr(g, name)) for name in Gaussians._fields}
    arrays.update(
        c2w=scene.c2w,
        intrinsics=scene.intrinsics,
        world_from_scene=scene.world_from_scene,
        inputs=np.asarray(scene.inputs, np.int64),
        targets=np.asarray(scene.targets, np.int64),
    )
    with open(path, "wb") as f:
        np.savez(f, header=np.frombuffer(json.dumps(header).encode(), np.uint8), **arrays)  # pyright: ignore[reportArgumentType] -- arrays by keyword; pyright matches the ** to allow_pickle


def load_gs(path: str) -> SavedScene:
    """Read a ``.gs`` file. One-line ``UserError`` naming the file if it is not a ``.gs``
    archive (what it looks like instead), truncated, of another version, inconsistent in its
    shapes, or holds a NaN or an infinity (the field and how many); ``MissingInputError`` if
    absent."""
    check_npz(path, "an llrmpp .gs file (from llrmpp reconstruct or refine)", ("header", *_ARRAYS))
    try:
        with np.load(path, allow_pickle=False) as z:
            header = json.loads(bytes(z["header"]).decode())
            if not isinstance(header, dict) or header.get("format") != GS_FORMAT:
                found = header.get("format") if isinstance(header, dict) else header
                raise UserError(f"{path}: not an llrmpp .gs file (format {found!r})")
            if header.get("version") != GS_VERSION:
                raise UserError(f"{path}: .gs version {header.get('version')}, this llrmpp reads version {GS_VERSION}")
            arrays = {k: z[k] for k in _ARRAYS}
    except UserError:
        raise
    except (zipfile.BadZipFile, EOFError, KeyError, OSError, ValueError, UnicodeDecodeError) as e:
        # ValueError: an object array (allow_pickle=False) or a damaged .npy header
        raise UserError(f"{path}: truncated or corrupt .gs file ({type(e).__name__}: {e})") from None
    _check_arrays(path, arrays)
    try:
        return SavedScene(
            gaussians=Gaussians(**{k: arrays[k] for k in Gaussians._fields}),
            model=from_dict(ModelConfig, header["model"]),
            c2w=arrays["c2w"],
            intrinsics=arrays["intrinsics"],
            world_from_scene=arrays["world_from_scene"],
            frame_names=tuple(str(n) for n in header["frame_names"]),
            inputs=arrays["inputs"],
            targets=arrays["targets"],
            image_hw=_hw(header["image_hw"]),
            resized_hw=_hw(header["resized_hw"]),
            crop_box=_box(header["crop_box"]),
            scene_path=str(header["scene_path"]),
            scene_format=str(header["scene_format"]),
        )
    except UserError as e:
        raise UserError(f"{path}: {e}") from None
    except (KeyError, TypeError, AttributeError, ValueError) as e:
        raise UserError(f"{path}: damaged .gs header ({type(e).__name__}: {e})") from None


def _ints(values, n: int) -> tuple[int, ...]:
    """``values`` as ``n`` non-negative ints (a header's sizes and crop box)."""
    out = tuple(int(v) for v in values)
    if len(out) != n or min(out) < 0:
        raise ValueError(f"expected {n} non-negative integers, got {values!r}")
    return out


def _hw(values) -> tuple[int, int]:
    h, w = _ints(values, 2)
    return h, w


def _box(values) -> tuple[int, int, int, int]:
    top, left, h, w = _ints(values, 4)
    return top, left, h, w


def _check_arrays(path: str, a: dict[str, np.ndarray]) -> None:
    """One line naming ``path`` unless the arrays are one scene's: N Gaussians, M frames,
    input and target indices among the frames, and every value finite."""
    n = a["means"].shape[0] if a["means"].ndim == 2 else -1
    m = a["c2w"].shape[0] if a["c2w"].ndim == 3 else -1
    want = {
        "means": (n, 3),
        "quats": (n, 4),
        "scales": (n, 2 if a["scales"].shape[1:] == (2,) else 3),  # 2: 2D Gaussians (SavedScene checks the model's)
        "opacities": (n,),
        "c2w": (m, 4, 4),
        "intrinsics": (m, 4),
        "world_from_scene": (4, 4),
    }
    for name, shape in want.items():
        if a[name].shape != shape or a[name].dtype.kind not in "fi":
            raise UserError(f"{path}: .gs field {name!r} has shape {a[name].shape} ({a[name].dtype}), expected {shape}")
    if a["features"].ndim != 2 or a["features"].shape[0] != n or a["features"].dtype.kind not in "fi":
        raise UserError(f"{path}: .gs field 'features' has shape {a['features'].shape}, expected ({n}, F)")
    for name in ("inputs", "targets"):
        idx = a[name]
        if idx.ndim != 1 or idx.dtype.kind not in "iu" or (idx.size and (idx.min() < 0 or idx.max() >= m)):
            raise UserError(f"{path}: .gs field {name!r} must be frame indices in [0, {m}), got {idx.tolist()[:8]}")
    check_finite(path, {k: a[k] for k in _ARRAYS}, "field ")
