"""COLMAP sparse models (``cameras``, ``images``, ``points3D``; binary ``.bin`` or ``.txt``),
read and written with pycolmap.

COLMAP stores world-to-camera poses in OpenCV camera axes and pixel coordinates with the
top-left pixel centre at (0.5, 0.5) -- the same conventions as :mod:`llrmpp_jax.geometry`.
Supported camera models (per image or shared): SIMPLE_PINHOLE, PINHOLE, SIMPLE_RADIAL,
RADIAL, OPENCV; their distortion is removed when images load.

COLMAP's binary reader trusts the counts it reads: a file cut short can still read as a
model (the missing bytes read as whatever was in memory) or loop for hours on a garbage
count. So each binary file's leading count is checked against the file's size before
pycolmap reads it, and the file's size against what was read after. A file pycolmap
rejects is named by reading the model's files one more at a time.
"""

from __future__ import annotations

import ctypes
import os
import re
import signal
import sys
import tempfile
import types
from dataclasses import dataclass
from typing import Any

import numpy as np

from llrmpp_jax.array_typing import Float, Int
from llrmpp_jax.data.formats.common import Missing, files_scene, write_frames
from llrmpp_jax.data.scene import Scene
from llrmpp_jax.errors import MissingInputError, UserError

_MODELS = ("SIMPLE_PINHOLE", "PINHOLE", "SIMPLE_RADIAL", "RADIAL", "OPENCV")
_PARTS = ("cameras", "images", "points3D")
# Bytes of each binary file's smallest record: a camera with 3 params (id, model, width,
# height, params); an image with a one-byte name and no points (id, quaternion, translation,
# camera id, name + NUL, point count); a point with an empty track (id, xyz, rgb, error,
# track length).
_MIN_RECORD = {"cameras": 4 + 4 + 8 + 8 + 3 * 8, "images": 4 + 7 * 8 + 4 + 2 + 8, "points3D": 8 + 3 * 8 + 3 + 8 + 8}
# What each text file holds, for the error when pycolmap rejects one.
_TEXT_LAYOUT = {
    "cameras": "a line per camera: CAMERA_ID MODEL WIDTH HEIGHT and as many PARAMS as the model has",
    "images": "two lines per image: IMAGE_ID QW QX QY QZ TX TY TZ CAMERA_ID NAME (a camera in cameras.txt), "
    "then X Y POINT3D_ID triples",
    "points3D": "a line per point: POINT3D_ID X Y Z R G B ERROR, "
    "then IMAGE_ID POINT2D_IDX pairs of images in images.txt",
}
# glog's failure handler, which pycolmap installs when it is imported.
_GLOG_SIGNALS = (signal.SIGILL, signal.SIGABRT, signal.SIGBUS, signal.SIGFPE, signal.SIGSEGV, signal.SIGTERM)


def import_pycolmap() -> types.ModuleType:
    """``import pycolmap`` without the crash handlers it installs process-wide.

    Importing pycolmap installs glog's failure signal handler for SIGSEGV, SIGABRT, SIGBUS,
    SIGILL, SIGFPE and SIGTERM. That handler walks the stack with ``backtrace()``, which
    deadlocks when the signal lands inside the C++ unwinder (it takes the unwinder's lock
    again): a later crash in the same process (``reconstruct --images`` runs the model after
    the poses; the test suite runs everything in two workers) then hangs forever instead of
    exiting. The C-level dispositions from before the import (Python's, faulthandler's or
    the default) are saved and put back with ``sigaction``; the struct is handled as opaque
    bytes, so no layout is assumed.
    """
    if "pycolmap" in sys.modules:
        return sys.modules["pycolmap"]
    libc = ctypes.CDLL(None, use_errno=True)
    saved = {sig: ctypes.create_string_buffer(512) for sig in _GLOG_SIGNALS}  # > sizeof(struct sigaction)
    for sig, buf in saved.items():
        if libc.sigaction(int(sig), None, buf) != 0:
            raise OSError(ctypes.get_errno(), f"sigaction({sig.name}) failed")
    import pycolmap

    for sig, buf in saved.items():
        if libc.sigaction(int(sig), buf, None) != 0:
            raise OSError(ctypes.get_errno(), f"sigaction({sig.name}) failed")
    return pycolmap


@dataclass(frozen=True)
class ColmapCamera:
    camera_id: int
    model: str
    width: int
    height: int
    params: Float[np.ndarray, " params"]

    def pinhole_and_distortion(self) -> tuple[np.ndarray, np.ndarray]:
        """``(fx, fy, cx, cy)`` and OpenCV ``(k1, k2, p1, p2, k3)`` of this camera."""
        p = self.params
        zeros = np.zeros(5)
        if self.model == "SIMPLE_PINHOLE":
            return np.array([p[0], p[0], p[1], p[2]]), zeros
        if self.model == "PINHOLE":
            return np.array(p[:4]), zeros
        if self.model == "SIMPLE_RADIAL":
            return np.array([p[0], p[0], p[1], p[2]]), np.array([p[3], 0.0, 0.0, 0.0, 0.0])
        if self.model == "RADIAL":
            return np.array([p[0], p[0], p[1], p[2]]), np.array([p[3], p[4], 0.0, 0.0, 0.0])
        return np.array(p[:4]), np.array([p[4], p[5], p[6], p[7], 0.0])  # OPENCV


@dataclass(frozen=True)
class ColmapImage:
    image_id: int
    c2w: Float[np.ndarray, "4 4"]  # OpenCV camera-to-world
    camera_id: int
    name: str
    xys: Float[np.ndarray, "pts 2"]  # observed (distorted) pixel coordinates
    point3d_ids: Int[np.ndarray, " pts"]  # -1 where the observation has no 3D point


@dataclass(frozen=True)
class ColmapPoint3D:
    point3d_id: int
    xyz: Float[np.ndarray, " 3"]
    rgb: Int[np.ndarray, " 3"]
    error: float
    image_ids: Int[np.ndarray, " track"]
    point2d_idxs: Int[np.ndarray, " track"]


def _message(e: Exception) -> str:
    """pycolmap's error on one line, without the C++ source location it starts with."""
    return re.sub(r"^\[[^\]]*\]\s*", "", " ".join(str(e).split()))[:200]


def _pycolmap_read(paths: dict[str, str], binary: bool, rig_dir: str | None) -> Any:
    """The ``pycolmap.Reconstruction`` of the files in ``paths`` (part -> file); a part
    not in it reads as empty. COLMAP reads a whole folder, so the files are linked into a
    temporary one next to empty stand-ins; ``rig_dir``: also link the ``rigs`` and
    ``frames`` files found there (without them COLMAP gives each image its own rig)."""
    pycolmap = import_pycolmap()
    ext = ".bin" if binary else ".txt"
    with tempfile.TemporaryDirectory() as tmp:
        for part in _PARTS:
            dst = os.path.join(tmp, part + ext)
            if part in paths:
                os.symlink(os.path.abspath(paths[part]), dst)
            else:
                with open(dst, "wb") as f:
                    f.write(bytes(8) if binary else b"")  # binary: a count of 0
        for part in ("rigs", "frames") if rig_dir is not None else ():
            if os.path.exists(src := os.path.join(rig_dir, part + ext)):  # pyright: ignore[reportArgumentType, reportCallIssue] -- the loop runs only when rig_dir is set
                os.symlink(os.path.abspath(src), os.path.join(tmp, part + ext))
        rec = pycolmap.Reconstruction()
        (rec.read_binary if binary else rec.read_text)(tmp)
    return rec


def _culprit(sparse_dir: str, paths: dict[str, str], binary: bool, error: Exception) -> UserError:
    """The error for a model pycolmap rejected, naming the first file that fails when the
    files are read one more at a time (cameras, then images, then points3D)."""
    kind = "binary" if binary else "text"
    parts = list(paths)
    for k in range(1, len(parts) + 1):
        try:
            _pycolmap_read({p: paths[p] for p in parts[:k]}, binary, None)
        except (ValueError, IndexError, RuntimeError, MemoryError) as e:
            part = parts[k - 1]
            expected = f"; expected {_TEXT_LAYOUT[part]}" if not binary else ""
            return UserError(f"{paths[part]}: not a valid COLMAP {kind} {part} file ({_message(e)}){expected}")
    return UserError(
        f"{sparse_dir}: COLMAP's rigs and frames files do not fit its cameras and images ({_message(error)})"
    )


def _check_count(path: str, part: str) -> None:
    """A binary file's leading record count fits in its size (else COLMAP loops on it)."""
    size = os.path.getsize(path)
    count = int(np.fromfile(path, "<u8", count=1)[0]) if size >= 8 else None
    if count is None or 8 + count * _MIN_RECORD[part] > size:
        needs = (
            "an 8-byte record count"
            if count is None
            else f"at least {8 + count * _MIN_RECORD[part]} for {count} {part}"
        )
        raise UserError(f"{path}: file is truncated ({size} bytes; needs {needs})")


def _binary_bytes(rec: Any, part: str) -> int:
    """Size (bytes) of the binary ``part`` file holding what ``rec`` read."""
    if part == "cameras":
        return 8 + sum(24 + 8 * len(c.params) for c in rec.cameras.values())
    if part == "images":
        return 8 + sum(64 + len(im.name.encode("utf-8")) + 1 + 8 + 24 * im.num_points2D() for im in rec.images.values())
    return 8 + sum(51 + 8 * p.track.length() for p in rec.points3D.values())


def _camera(path: str, cam: Any) -> ColmapCamera:
    name, cid = cam.model.name, int(cam.camera_id)
    if name not in _MODELS:
        raise UserError(f"{path}: camera {cid} has unsupported model {name!r} (supported: {list(_MODELS)})")
    return ColmapCamera(cid, name, int(cam.width), int(cam.height), np.array(cam.params, dtype=np.float64))


def _c2w(im: Any) -> Float[np.ndarray, "4 4"]:
    out = np.eye(4)
    out[:3] = im.cam_from_world().inverse().matrix()
    return out


def _image(im: Any) -> ColmapImage:
    pts = im.points2D
    xys = np.array([p.xy for p in pts], dtype=np.float64).reshape(-1, 2)
    ids = np.array([p.point3D_id if p.has_point3D() else -1 for p in pts], dtype=np.int64)
    return ColmapImage(int(im.image_id), _c2w(im), int(im.camera_id), im.name, xys, ids)


def _point(pid: int, p: Any) -> ColmapPoint3D:
    track = np.array([(e.image_id, e.point2D_idx) for e in p.track.elements], dtype=np.int64).reshape(-1, 2)
    return ColmapPoint3D(
        int(pid),
        np.array(p.xyz, dtype=np.float64),
        np.array(p.color, dtype=np.int64),
        float(p.error),
        track[:, 0],
        track[:, 1],
    )


def _read_checked(sparse_dir: str, with_points: bool) -> tuple[Any, dict[int, ColmapCamera]]:
    """The ``pycolmap.Reconstruction`` in ``sparse_dir`` (binary if ``cameras.bin`` exists,
    else text; empty points unless ``with_points``) and its cameras, checked."""
    binary = os.path.exists(os.path.join(sparse_dir, "cameras.bin"))
    ext = ".bin" if binary else ".txt"
    paths = {part: os.path.join(sparse_dir, part + ext) for part in _PARTS[: 3 if with_points else 2]}
    for path in paths.values():
        if not os.path.exists(path):
            raise MissingInputError(f"COLMAP model file not found: {path}")
    if binary:
        for part, path in paths.items():
            _check_count(path, part)
    try:
        rec = _pycolmap_read(paths, binary, sparse_dir)
    except (ValueError, IndexError, RuntimeError, MemoryError) as e:
        raise _culprit(sparse_dir, paths, binary, e) from None
    for part, path in paths.items():
        if binary and (size := os.path.getsize(path)) != (expected := _binary_bytes(rec, part)):
            raise UserError(
                f"{path}: {size} bytes, but the {part} it lists take {expected} "
                "(the file is cut short or not in COLMAP's binary format)"
            )
    return rec, {int(cid): _camera(paths["cameras"], c) for cid, c in rec.cameras.items()}


def read_colmap_model(
    sparse_dir: str, with_points: bool = True
) -> tuple[dict[int, ColmapCamera], dict[int, ColmapImage], dict[int, ColmapPoint3D]]:
    """Read ``cameras``, ``images`` (and ``points3D``) from ``sparse_dir``, binary if
    ``cameras.bin`` exists, else text. Returns dicts keyed by id; images are the registered
    ones. Without points, ``points3D`` need not exist and is not read."""
    rec, cams = _read_checked(sparse_dir, with_points)
    imgs = {int(iid): _image(im) for iid, im in rec.images.items() if im.has_pose}
    pts = {int(pid): _point(pid, p) for pid, p in rec.points3D.items()}
    return cams, imgs, pts


def read_colmap_scene(sparse_dir: str, image_dir: str, undistort: bool = True, missing: Missing = "skip") -> Scene:
    """A :class:`Scene` over the registered images of a COLMAP model, ordered by image
    name (the path under ``image_dir``), with each image's own camera (intrinsics and
    distortion)."""
    rec, cams = _read_checked(sparse_dir, with_points=False)
    order = sorted((im for im in rec.images.values() if im.has_pose), key=lambda im: im.name)
    intr, dist, hw = [], [], []
    for im in order:
        if im.camera_id not in cams:
            raise UserError(
                f"{sparse_dir}: image {im.name!r} refers to camera {im.camera_id}, which is not in the model"
            )
        cam = cams[im.camera_id]
        k, d = cam.pinhole_and_distortion()
        intr.append(k)
        dist.append(d)
        hw.append([cam.height, cam.width])
    distortion = np.asarray(dist).reshape(-1, 5)
    return files_scene(
        name=os.path.basename(os.path.normpath(os.path.join(sparse_dir, "..", ".."))),
        source=sparse_dir,
        image_paths=[os.path.join(image_dir, im.name) for im in order],
        c2w=np.stack([_c2w(im) for im in order]) if order else np.zeros((0, 4, 4)),
        intrinsics=np.asarray(intr).reshape(-1, 4),
        declared_hw=np.asarray(hw).reshape(-1, 2),
        distortion=distortion if undistort and distortion.any() else None,
        missing=missing,
    )


def write_colmap_scene(scene: Scene, out_dir: str, binary: bool = True, image_ext: str = ".png", bits: int = 16) -> str:
    """Write ``scene`` as ``out_dir/images/`` + ``out_dir/sparse/0/`` with one PINHOLE camera
    (and one rig and frame) per image and an empty ``points3D``. Returns the sparse folder.
    (COLMAP models hold no depth maps.)"""
    pycolmap = import_pycolmap()
    n = len(scene)
    names = [f"{i:05d}{image_ext}" for i in range(n)]
    write_frames(scene, os.path.join(out_dir, "images"), names, None, bits=bits)
    sparse = os.path.join(out_dir, "sparse", "0")
    os.makedirs(sparse, exist_ok=True)
    w2c = np.linalg.inv(scene.c2w)
    rec = pycolmap.Reconstruction()
    for i in range(n):
        h, w = scene.hw[i].tolist()
        rec.add_camera_with_trivial_rig(
            pycolmap.Camera(
                model="PINHOLE", width=w, height=h, params=np.asarray(scene.intrinsics[i], np.float64), camera_id=i + 1
            )
        )
        rec.add_image_with_trivial_frame(
            pycolmap.Image(name=names[i], camera_id=i + 1, image_id=i + 1),
            pycolmap.Rigid3d(pycolmap.Rotation3d(w2c[i, :3, :3]), w2c[i, :3, 3]),
        )
    (rec.write_binary if binary else rec.write_text)(sparse)
    return sparse
