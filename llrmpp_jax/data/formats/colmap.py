"""COLMAP sparse models (``cameras``, ``images``, ``points3D``; binary ``.bin`` or ``.txt``).

COLMAP stores world-to-camera poses as a unit quaternion ``(qw, qx, qy, qz)`` and a
translation, in OpenCV camera axes, and pixel coordinates with the top-left pixel centre at
(0.5, 0.5) -- the same conventions as :mod:`llrmpp_jax.geometry`. Supported camera models
(per image or shared): SIMPLE_PINHOLE, PINHOLE, SIMPLE_RADIAL, RADIAL, OPENCV; their
distortion is removed when images load.
"""

from __future__ import annotations

import os
import struct
from dataclasses import dataclass

import numpy as np

from llrmpp_jax.array_typing import Float, Int
from llrmpp_jax.data.formats.common import Missing, files_scene, write_frames
from llrmpp_jax.data.scene import Scene
from llrmpp_jax.errors import MissingInputError, UserError

# model id -> (name, number of params)
_MODELS = {0: ("SIMPLE_PINHOLE", 3), 1: ("PINHOLE", 4), 2: ("SIMPLE_RADIAL", 4), 3: ("RADIAL", 5), 4: ("OPENCV", 8)}
_MODEL_IDS = {name: (mid, npar) for mid, (name, npar) in _MODELS.items()}


@dataclass(frozen=True)
class ColmapCamera:
    camera_id: int
    model: str
    width: int
    height: int
    params: Float[np.ndarray, "params"]

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
    qvec: Float[np.ndarray, "4"]  # world-to-camera rotation, (w, x, y, z)
    tvec: Float[np.ndarray, "3"]  # world-to-camera translation
    camera_id: int
    name: str
    xys: Float[np.ndarray, "pts 2"]  # observed (distorted) pixel coordinates
    point3d_ids: Int[np.ndarray, "pts"]  # -1 where the observation has no 3D point

    def c2w(self) -> Float[np.ndarray, "4 4"]:
        """OpenCV camera-to-world."""
        rot = qvec_to_rotmat(self.qvec)
        out = np.eye(4)
        out[:3, :3] = rot.T
        out[:3, 3] = -rot.T @ self.tvec
        return out


@dataclass(frozen=True)
class ColmapPoint3D:
    point3d_id: int
    xyz: Float[np.ndarray, "3"]
    rgb: Int[np.ndarray, "3"]
    error: float
    image_ids: Int[np.ndarray, "track"]
    point2d_idxs: Int[np.ndarray, "track"]


def qvec_to_rotmat(q: Float[np.ndarray, "4"]) -> Float[np.ndarray, "3 3"]:
    """Rotation matrix of a quaternion ``(w, x, y, z)`` (normalised first)."""
    w, x, y, z = np.asarray(q, dtype=np.float64) / np.linalg.norm(q)
    return np.array([
        [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
        [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
        [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
    ])


def rotmat_to_qvec(rot: Float[np.ndarray, "3 3"]) -> Float[np.ndarray, "4"]:
    """Unit quaternion ``(w, x, y, z)`` with ``w >= 0`` of a rotation matrix (the dominant
    eigenvector of Bar-Itzhack's symmetric 4x4 matrix, as COLMAP's scripts compute it)."""
    r = np.asarray(rot, dtype=np.float64)
    k = np.array([
        [r[0, 0] - r[1, 1] - r[2, 2], 0, 0, 0],
        [r[1, 0] + r[0, 1], r[1, 1] - r[0, 0] - r[2, 2], 0, 0],
        [r[2, 0] + r[0, 2], r[2, 1] + r[1, 2], r[2, 2] - r[0, 0] - r[1, 1], 0],
        [r[2, 1] - r[1, 2], r[0, 2] - r[2, 0], r[1, 0] - r[0, 1], r[0, 0] + r[1, 1] + r[2, 2]],
    ]) / 3.0
    vals, vecs = np.linalg.eigh(k)
    q = vecs[[3, 0, 1, 2], np.argmax(vals)]
    return q if q[0] >= 0 else -q


class _Reader:
    def __init__(self, path: str):
        self.path = path
        with open(path, "rb") as f:
            self.buf = f.read()
        self.pos = 0

    def take(self, fmt: str) -> tuple:
        size = struct.calcsize(fmt)
        if self.pos + size > len(self.buf):
            raise UserError(f"{self.path}: file is truncated (needed {size} bytes at offset {self.pos})")
        out = struct.unpack_from(fmt, self.buf, self.pos)
        self.pos += size
        return out

    def name(self) -> str:
        end = self.buf.find(b"\x00", self.pos)
        if end < 0:
            raise UserError(f"{self.path}: file is truncated inside an image name")
        out = self.buf[self.pos : end].decode("utf-8")
        self.pos = end + 1
        return out


def _model(path: str, camera_id: int, model_id: int | str) -> tuple[str, int]:
    if isinstance(model_id, str):
        if model_id not in _MODEL_IDS:
            raise UserError(f"{path}: camera {camera_id} has unsupported model {model_id!r} (supported: {list(_MODEL_IDS)})")
        return model_id, _MODEL_IDS[model_id][1]
    if model_id not in _MODELS:
        raise UserError(f"{path}: camera {camera_id} has unsupported model id {model_id} (supported: {_MODELS})")
    return _MODELS[model_id]


def _read_cameras_bin(path: str) -> dict[int, ColmapCamera]:
    r = _Reader(path)
    cams = {}
    for _ in range(r.take("<Q")[0]):
        cid, mid, w, h = r.take("<iiQQ")
        name, npar = _model(path, cid, mid)
        cams[cid] = ColmapCamera(cid, name, int(w), int(h), np.array(r.take(f"<{npar}d")))
    return cams


def _read_images_bin(path: str) -> dict[int, ColmapImage]:
    r = _Reader(path)
    imgs = {}
    for _ in range(r.take("<Q")[0]):
        iid, *qt, cid = r.take("<i7di")
        name = r.name()
        npts = r.take("<Q")[0]
        flat = np.array(r.take("<" + "ddq" * npts), dtype=np.float64).reshape(npts, 3)
        imgs[iid] = ColmapImage(iid, np.array(qt[:4]), np.array(qt[4:]), cid, name, flat[:, :2],
                                flat[:, 2].astype(np.int64))
    return imgs


def _read_points_bin(path: str) -> dict[int, ColmapPoint3D]:
    r = _Reader(path)
    pts = {}
    for _ in range(r.take("<Q")[0]):
        pid, x, y, z, cr, cg, cb, err, tlen = r.take("<Q3d3BdQ")
        track = np.array(r.take("<" + "ii" * tlen), dtype=np.int64).reshape(tlen, 2)
        pts[pid] = ColmapPoint3D(pid, np.array([x, y, z]), np.array([cr, cg, cb]), err, track[:, 0], track[:, 1])
    return pts


def _text_lines(path: str) -> list[str]:
    with open(path) as f:
        return [ln.strip() for ln in f if ln.strip() and not ln.lstrip().startswith("#")]


def _read_cameras_txt(path: str) -> dict[int, ColmapCamera]:
    cams = {}
    for ln in _text_lines(path):
        el = ln.split()
        cid = int(el[0])
        name, npar = _model(path, cid, el[1])
        if len(el) != 4 + npar:
            raise UserError(f"{path}: camera {cid} ({name}) needs {npar} params, got {len(el) - 4}")
        cams[cid] = ColmapCamera(cid, name, int(el[2]), int(el[3]), np.array(el[4:], dtype=np.float64))
    return cams


def _read_images_txt(path: str) -> dict[int, ColmapImage]:
    with open(path) as f:
        lines = [ln.rstrip("\n") for ln in f if not ln.lstrip().startswith("#")]
    imgs = {}
    k = 0
    while k < len(lines):
        if not lines[k].strip():
            k += 1
            continue
        el = lines[k].split(maxsplit=9)
        pts = lines[k + 1].split() if k + 1 < len(lines) else []
        flat = np.array(pts, dtype=np.float64).reshape(-1, 3)
        iid = int(el[0])
        imgs[iid] = ColmapImage(iid, np.array(el[1:5], dtype=np.float64), np.array(el[5:8], dtype=np.float64),
                                int(el[8]), el[9], flat[:, :2], flat[:, 2].astype(np.int64))
        k += 2
    return imgs


def _read_points_txt(path: str) -> dict[int, ColmapPoint3D]:
    pts = {}
    for ln in _text_lines(path):
        el = ln.split()
        pid = int(el[0])
        track = np.array(el[8:], dtype=np.int64).reshape(-1, 2)
        pts[pid] = ColmapPoint3D(pid, np.array(el[1:4], dtype=np.float64), np.array(el[4:7], dtype=np.int64),
                                 float(el[7]), track[:, 0], track[:, 1])
    return pts


def read_colmap_model(
    sparse_dir: str, with_points: bool = True
) -> tuple[dict[int, ColmapCamera], dict[int, ColmapImage], dict[int, ColmapPoint3D]]:
    """Parse ``cameras``, ``images`` (and ``points3D``) from ``sparse_dir``, binary if
    ``cameras.bin`` exists, else text. Returns dicts keyed by id."""
    binary = os.path.exists(os.path.join(sparse_dir, "cameras.bin"))
    ext = ".bin" if binary else ".txt"
    paths = {key: os.path.join(sparse_dir, key + ext) for key in ("cameras", "images", "points3D")}
    for key in ("cameras", "images") + (("points3D",) if with_points else ()):
        if not os.path.exists(paths[key]):
            raise MissingInputError(f"COLMAP model file not found: {paths[key]}")
    try:
        if binary:
            cams, imgs = _read_cameras_bin(paths["cameras"]), _read_images_bin(paths["images"])
            pts = _read_points_bin(paths["points3D"]) if with_points else {}
        else:
            cams, imgs = _read_cameras_txt(paths["cameras"]), _read_images_txt(paths["images"])
            pts = _read_points_txt(paths["points3D"]) if with_points else {}
    except (IndexError, UnicodeDecodeError, struct.error) as e:
        raise UserError(f"{sparse_dir}: malformed COLMAP model ({type(e).__name__}: {e})") from None
    return cams, imgs, pts


def read_colmap_scene(
    sparse_dir: str, image_dir: str, undistort: bool = True, missing: Missing = "skip"
) -> Scene:
    """A :class:`Scene` over the registered images of a COLMAP model, ordered by image
    name, with each image's own camera (intrinsics and distortion)."""
    cams, imgs, _ = read_colmap_model(sparse_dir, with_points=False)
    order = sorted(imgs.values(), key=lambda im: im.name)
    intr, dist, hw = [], [], []
    for im in order:
        if im.camera_id not in cams:
            raise UserError(f"{sparse_dir}: image {im.name!r} refers to camera {im.camera_id}, which is not in the model")
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
        c2w=np.stack([im.c2w() for im in order]) if order else np.zeros((0, 4, 4)),
        intrinsics=np.asarray(intr).reshape(-1, 4),
        declared_hw=np.asarray(hw).reshape(-1, 2),
        distortion=distortion if undistort and distortion.any() else None,
        missing=missing,
    )


def write_colmap_scene(scene: Scene, out_dir: str, binary: bool = True, image_ext: str = ".png", bits: int = 16) -> str:
    """Write ``scene`` as ``out_dir/images/`` + ``out_dir/sparse/0/`` with one PINHOLE camera
    per image and an empty ``points3D``. Returns the sparse folder. (COLMAP models hold no
    depth maps.)"""
    n = len(scene)
    names = [f"{i:05d}{image_ext}" for i in range(n)]
    write_frames(scene, os.path.join(out_dir, "images"), names, None, bits=bits)
    sparse = os.path.join(out_dir, "sparse", "0")
    os.makedirs(sparse, exist_ok=True)
    w2c = np.linalg.inv(scene.c2w)
    qvecs = [rotmat_to_qvec(w2c[i, :3, :3]) for i in range(n)]
    if binary:
        with open(os.path.join(sparse, "cameras.bin"), "wb") as f:
            f.write(struct.pack("<Q", n))
            for i in range(n):
                h, w = scene.hw[i].tolist()
                f.write(struct.pack("<iiQQ4d", i + 1, _MODEL_IDS["PINHOLE"][0], w, h, *scene.intrinsics[i]))
        with open(os.path.join(sparse, "images.bin"), "wb") as f:
            f.write(struct.pack("<Q", n))
            for i in range(n):
                f.write(struct.pack("<i7di", i + 1, *qvecs[i], *w2c[i, :3, 3], i + 1))
                f.write(names[i].encode("utf-8") + b"\x00" + struct.pack("<Q", 0))
        with open(os.path.join(sparse, "points3D.bin"), "wb") as f:
            f.write(struct.pack("<Q", 0))
    else:
        with open(os.path.join(sparse, "cameras.txt"), "w") as f:
            f.write("# CAMERA_ID, MODEL, WIDTH, HEIGHT, PARAMS[]\n")
            for i in range(n):
                h, w = scene.hw[i].tolist()
                f.write(f"{i + 1} PINHOLE {w} {h} " + " ".join(repr(float(v)) for v in scene.intrinsics[i]) + "\n")
        with open(os.path.join(sparse, "images.txt"), "w") as f:
            f.write("# IMAGE_ID, QW, QX, QY, QZ, TX, TY, TZ, CAMERA_ID, NAME\n# POINTS2D[] as (X, Y, POINT3D_ID)\n")
            for i in range(n):
                vals = " ".join(repr(float(v)) for v in (*qvecs[i], *w2c[i, :3, 3]))
                f.write(f"{i + 1} {vals} {i + 1} {names[i]}\n\n")
        with open(os.path.join(sparse, "points3D.txt"), "w") as f:
            f.write("# POINT3D_ID, X, Y, Z, R, G, B, ERROR, TRACK[] as (IMAGE_ID, POINT2D_IDX)\n")
    return sparse
