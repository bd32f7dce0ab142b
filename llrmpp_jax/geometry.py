"""Camera geometry: OpenCV cameras, pixel rays, Plücker embeddings, intrinsics under
resize/crop, projection, and Long-LRM's scene normalisation.

Conventions (one place for the whole project):

* Cameras are **OpenCV**: x right, y down, z forward. ``c2w`` is a 4x4 camera-to-world
  matrix ``[[R, t], [0, 0, 0, 1]]``; ``t`` is the camera centre in world units.
* Intrinsics are ``[fx, fy, cx, cy]`` in **pixels**. The centre of pixel (row i, column j)
  is at continuous image coordinate ``(j + 0.5, i + 0.5)`` (COLMAP and Long-LRM agree),
  so scaling an image by ``s`` scales every intrinsic by ``s`` exactly.
* Depth is **z-depth** (distance along the camera's forward axis), in world units.

Every function takes NumPy or JAX arrays and returns the same kind (JAX inside ``jit``);
the array library is chosen from the inputs. Nothing promotes dtypes implicitly: the
result has the dtype of the camera matrices (float32 unless they are float64).
"""

from __future__ import annotations

from collections.abc import Sequence
from types import ModuleType

import jax
import jax.numpy as jnp
import numpy as np

from llrmpp_jax.array_typing import ArrayLike, Float, IntLike
from llrmpp_jax.errors import UserError

_GL_CV_FLIP = (1.0, -1.0, -1.0, 1.0)


def _xp(*arrays: object) -> ModuleType:
    """``jax.numpy`` if any argument is a JAX array (or tracer), else ``numpy``."""
    return jnp if any(isinstance(a, jax.Array) for a in arrays) else np


def _float_dtype(x: ArrayLike) -> np.dtype:
    """float64 stays float64; every other dtype (ints, float32, bf16) computes in float32."""
    return np.dtype(np.float64) if np.dtype(x.dtype) == np.float64 else np.dtype(np.float32)


def _check_trailing(x: ArrayLike, trailing: tuple[int, ...], name: str, letters: str) -> None:
    if x.ndim < len(trailing) or tuple(x.shape[x.ndim - len(trailing) :]) != trailing:
        raise ValueError(f"{name}: expected shape [..., {letters}], got {tuple(x.shape)}")


def pixel_rays(
    c2w: Float[ArrayLike, "... 4 4"], intrinsics: Float[ArrayLike, "... 4"], height: int, width: int
) -> tuple[Float[ArrayLike, "... H W 3"], Float[ArrayLike, "... H W 3"]]:
    """Ray origin and unit direction through every pixel centre.

    ``d = normalize(R @ [(x + 0.5 - cx) / fx, (y + 0.5 - cy) / fy, 1])`` with x the
    column and y the row; ``o`` is the camera centre ``c2w[:3, 3]`` (Long-LRM / LVSM).

    Args:
      c2w: ``[..., 4, 4]`` OpenCV camera-to-world.
      intrinsics: ``[..., 4]`` pixel ``(fx, fy, cx, cy)``; same leading shape as ``c2w``.
      height, width: image size H, W in pixels.

    Returns:
      ``(origins [..., H, W, 3], directions [..., H, W, 3])`` in world units.
    """
    xp = _xp(c2w, intrinsics)
    _check_trailing(c2w, (4, 4), "c2w", "4, 4")
    _check_trailing(intrinsics, (4,), "intrinsics", "4")
    batch = tuple(c2w.shape[:-2])
    if tuple(intrinsics.shape[:-1]) != batch:
        raise ValueError(
            f"intrinsics: expected shape [{', '.join(map(str, batch + (4,)))}] to match c2w "
            f"{tuple(c2w.shape)}, got {tuple(intrinsics.shape)}"
        )
    dtype = _float_dtype(c2w)
    nb = len(batch)
    x = xp.broadcast_to(xp.arange(width, dtype=dtype)[None, :] + 0.5, (height, width))
    y = xp.broadcast_to(xp.arange(height, dtype=dtype)[:, None] + 0.5, (height, width))
    uv = xp.reshape(xp.stack([x, y], axis=-1), (1,) * nb + (height, width, 2))
    return rays_through_pixels(c2w[..., None, None, :, :], intrinsics[..., None, None, :], uv)


def rays_through_pixels(
    c2w: Float[ArrayLike, "... 4 4"], intrinsics: Float[ArrayLike, "... 4"], uv: Float[ArrayLike, "... 2"]
) -> tuple[Float[ArrayLike, "... 3"], Float[ArrayLike, "... 3"]]:
    """Ray origin and unit direction through continuous pixel coordinates ``uv = (x, y)``.

    ``d = normalize(R @ [(x - cx) / fx, (y - cy) / fy, 1])``; pixel (i, j)'s centre is
    ``(j + 0.5, i + 0.5)``. The leading dims of ``c2w``, ``intrinsics`` and ``uv`` must have
    the same rank and broadcast against each other (size-1 axes stretch).
    """
    xp = _xp(c2w, intrinsics, uv)
    _check_trailing(c2w, (4, 4), "c2w", "4, 4")
    _check_trailing(intrinsics, (4,), "intrinsics", "4")
    _check_trailing(uv, (2,), "uv", "2")
    if not (c2w.ndim - 2 == intrinsics.ndim - 1 == uv.ndim - 1):
        raise ValueError(
            f"rays_through_pixels: leading ranks differ: c2w {tuple(c2w.shape)}, "
            f"intrinsics {tuple(intrinsics.shape)}, uv {tuple(uv.shape)}"
        )
    dtype = _float_dtype(c2w)
    c2w = xp.asarray(c2w, dtype=dtype)
    k = xp.asarray(intrinsics, dtype=dtype)
    uv = xp.asarray(uv, dtype=dtype)
    u = (uv[..., 0] - k[..., 2]) / k[..., 0]
    v = (uv[..., 1] - k[..., 3]) / k[..., 1]
    cam = xp.stack([u, v, xp.ones_like(u)], axis=-1)
    directions = xp.sum(c2w[..., :3, :3] * cam[..., None, :], axis=-1)
    directions = directions / xp.linalg.norm(directions, axis=-1, keepdims=True)
    origins = xp.broadcast_to(c2w[..., :3, 3], directions.shape)
    return origins, directions


def plucker(origins: Float[ArrayLike, "... 3"], directions: Float[ArrayLike, "... 3"]) -> Float[ArrayLike, "... 6"]:
    """Plücker ray embedding ``[o x d, d]`` (Long-LRM / LVSM channel order), ``[..., 6]``."""
    xp = _xp(origins, directions)
    _check_trailing(origins, (3,), "origins", "3")
    if tuple(directions.shape) != tuple(origins.shape):
        raise ValueError(
            f"directions: expected shape {tuple(origins.shape)} (same as origins), got {tuple(directions.shape)}"
        )
    return xp.concatenate([xp.cross(origins, directions), directions], axis=-1)


def resize_intrinsics(
    intrinsics: Float[ArrayLike, "... 4"], old_hw: Sequence[IntLike], new_hw: Sequence[IntLike]
) -> Float[ArrayLike, "... 4"]:
    """Intrinsics after resizing the image from ``old_hw`` = (H, W) to ``new_hw``.

    Exact for any resampler that maps the image extent onto the new extent (pixel centres
    at +0.5): every continuous coordinate scales by ``W'/W`` horizontally, ``H'/H`` vertically.
    """
    xp = _xp(intrinsics)
    _check_trailing(intrinsics, (4,), "intrinsics", "4")
    (h0, w0), (h1, w1) = old_hw, new_hw
    if min(h0, w0, h1, w1) <= 0:
        raise ValueError(f"resize_intrinsics: sizes must be positive, got old_hw={old_hw}, new_hw={new_hw}")
    dtype = _float_dtype(intrinsics)
    sx, sy = w1 / w0, h1 / h0
    scale = xp.asarray([sx, sy, sx, sy], dtype=dtype)
    return xp.asarray(intrinsics, dtype=dtype) * xp.reshape(scale, (1,) * (intrinsics.ndim - 1) + (4,))


def crop_intrinsics(
    intrinsics: Float[ArrayLike, "... 4"], top: float | ArrayLike, left: float | ArrayLike
) -> Float[ArrayLike, "... 4"]:
    """Intrinsics after cropping rows ``[top:]`` and columns ``[left:]`` (pixels, may be
    per-view arrays of the leading shape): the principal point moves by ``-(left, top)``."""
    xp = _xp(intrinsics, top, left)
    _check_trailing(intrinsics, (4,), "intrinsics", "4")
    dtype = _float_dtype(intrinsics)
    intrinsics = xp.asarray(intrinsics, dtype=dtype)
    batch = tuple(intrinsics.shape[:-1])
    top = xp.broadcast_to(xp.asarray(top, dtype=dtype), batch)
    left = xp.broadcast_to(xp.asarray(left, dtype=dtype), batch)
    zeros = xp.zeros(batch, dtype=dtype)
    return intrinsics - xp.stack([zeros, zeros, left, top], axis=-1)


def project_points(
    points: Float[ArrayLike, "... pts 3"], c2w: Float[ArrayLike, "... 4 4"], intrinsics: Float[ArrayLike, "... 4"]
) -> tuple[Float[ArrayLike, "... pts 2"], Float[ArrayLike, "... pts"]]:
    """Project world points into a camera.

    Returns ``(pixels [..., P, 2], depth [..., P])``: continuous pixel coordinates
    ``(x, y)`` (pixel (i, j) covers ``[j, j+1) x [i, i+1)``) and z-depth. Points behind the
    camera get negative depth; their pixel coordinates are meaningless.
    """
    xp = _xp(points, c2w, intrinsics)
    _check_trailing(points, (3,), "points", "P, 3")
    _check_trailing(c2w, (4, 4), "c2w", "4, 4")
    _check_trailing(intrinsics, (4,), "intrinsics", "4")
    dtype = _float_dtype(c2w)
    points = xp.asarray(points, dtype=dtype)
    rot = xp.asarray(c2w[..., :3, :3], dtype=dtype)
    cam = xp.einsum("...ji,...pj->...pi", rot, points - xp.asarray(c2w[..., None, :3, 3], dtype=dtype))
    depth = cam[..., 2]
    k = xp.asarray(intrinsics, dtype=dtype)[..., None, :]
    px = k[..., 0] * cam[..., 0] / depth + k[..., 2]
    py = k[..., 1] * cam[..., 1] / depth + k[..., 3]
    return xp.stack([px, py], axis=-1), depth


def unproject_depth(
    depth: Float[ArrayLike, "... H W"], c2w: Float[ArrayLike, "... 4 4"], intrinsics: Float[ArrayLike, "... 4"]
) -> Float[ArrayLike, "... H W 3"]:
    """World points seen at every pixel centre given z-depth, ``[..., H, W, 3]``."""
    xp = _xp(depth, c2w, intrinsics)
    if depth.ndim < 2:
        raise ValueError(f"depth: expected shape [..., H, W], got {tuple(depth.shape)}")
    height, width = depth.shape[-2:]
    origins, directions = pixel_rays(c2w, intrinsics, height, width)
    dtype = origins.dtype
    # Unit ray d has forward component d_z = (R^T d)_z; the point at z-depth z is o + d * z / d_z.
    forward = xp.asarray(c2w[..., None, None, :3, 2], dtype=dtype)
    dz = xp.sum(directions * forward, axis=-1, keepdims=True)
    return origins + directions * (xp.asarray(depth, dtype=dtype)[..., None] / dz)


def opengl_to_opencv(c2w: Float[ArrayLike, "... 4 4"]) -> Float[ArrayLike, "... 4 4"]:
    """Camera axes OpenGL/NeRF (x right, y up, z backward) -> OpenCV: ``c2w @ diag(1,-1,-1,1)``."""
    xp = _xp(c2w)
    _check_trailing(c2w, (4, 4), "c2w", "4, 4")
    flip = xp.asarray(_GL_CV_FLIP, dtype=_float_dtype(c2w))
    return xp.asarray(c2w, dtype=_float_dtype(c2w)) * xp.reshape(flip, (1,) * (c2w.ndim - 1) + (4,))


def opencv_to_opengl(c2w: Float[ArrayLike, "... 4 4"]) -> Float[ArrayLike, "... 4 4"]:
    """OpenCV -> OpenGL camera axes; the flip is its own inverse, so this equals
    :func:`opengl_to_opencv` (named separately so call sites say which way they go)."""
    return opengl_to_opencv(c2w)


def normalize_scene(
    input_c2w: Float[ArrayLike, "V 4 4"],
    *others: Float[ArrayLike, "T 4 4"],
    scene_scale: float = 1.0,
    rescale: bool = True,
) -> tuple[ArrayLike, ...]:
    """Long-LRM §3.4 pose normalisation, computed from the input views only.

    1. centre = mean input camera position; fwd = normalize(mean z-axis);
       down = normalize(mean y-axis orthogonalised against fwd); right = down x fwd.
    2. Rotate/translate so that this mean pose is the identity.
    3. Scale translations by ``s = 1 / (scene_scale * max |t|)`` over all input
       coordinates, so input cameras lie in ``[-1, 1]^3`` (``s = 1`` if all inputs coincide).

    Args:
      input_c2w: ``[V, 4, 4]`` OpenCV camera-to-world of the input views.
      *others: any number of ``[T, 4, 4]`` stacks (e.g. targets) moved by the same transform.
      scene_scale: Long-LRM's ``data.scene_scale`` (LVSM uses 1.35).
      rescale: False skips step 3 (``s = 1``: a rigid motion, world units kept). For
        metric data with depth targets: with step 3 each window's depths are in its own
        units (x ``1 / max |t|`` of its inputs), which varies ~3x between short windows.

    Returns:
      ``(input_c2w', *others', transform [4, 4], scale [])``. ``transform`` is the
      similarity ``[[s R^T, -s R^T c], [0, 1]]`` mapping world points to normalised points,
      so depth scales by ``scale``; :func:`denormalize_poses` undoes it.
    """
    xp = _xp(input_c2w, *others)
    _check_trailing(input_c2w, (4, 4), "input_c2w", "4, 4")
    if input_c2w.ndim != 3 or input_c2w.shape[0] < 1:
        raise ValueError(f"input_c2w: expected shape [V, 4, 4] with V >= 1, got {tuple(input_c2w.shape)}")
    for i, o in enumerate(others):
        _check_trailing(o, (4, 4), f"others[{i}]", "4, 4")
    dtype = _float_dtype(input_c2w)
    input_c2w = xp.asarray(input_c2w, dtype=dtype)
    centre = xp.mean(input_c2w[:, :3, 3], axis=0)
    fwd = xp.mean(input_c2w[:, :3, 2], axis=0)
    fwd = fwd / xp.linalg.norm(fwd)
    down = xp.mean(input_c2w[:, :3, 1], axis=0)
    down = down - xp.sum(down * fwd) * fwd
    down = down / xp.linalg.norm(down)
    right = xp.cross(down, fwd)
    rot_t = xp.stack([right, down, fwd], axis=0)  # R_avg^T: rows are the mean axes
    t_rel = xp.einsum("ij,vj->vi", rot_t, input_c2w[:, :3, 3] - centre[None, :])
    extent = xp.max(xp.abs(t_rel)) * scene_scale
    scale = xp.where(extent > 1e-12, 1.0 / xp.where(extent > 1e-12, extent, 1.0), 1.0).astype(dtype)
    if not rescale:
        scale = xp.ones_like(scale)
    top = xp.concatenate([scale * rot_t, (-scale * (rot_t @ centre))[:, None]], axis=1)
    transform = xp.concatenate([top, xp.asarray([[0.0, 0.0, 0.0, 1.0]], dtype=dtype)], axis=0)
    outs = tuple(_apply_similarity(transform, scale, xp.asarray(c, dtype=dtype), xp) for c in (input_c2w, *others))
    return (*outs, transform, scale)


def _apply_similarity(transform: ArrayLike, scale: float | ArrayLike, c2w: ArrayLike, xp: ModuleType) -> ArrayLike:
    """c2w' with rotation ``R_s R / s`` (still orthonormal) and centre ``T @ t``."""
    rot = xp.einsum("ij,...jk->...ik", transform[:3, :3] / scale, c2w[..., :3, :3])
    t = xp.einsum("ij,...j->...i", transform[:3, :3], c2w[..., :3, 3])
    t = t + xp.reshape(transform[:3, 3], (1,) * (t.ndim - 1) + (3,))
    top = xp.concatenate([rot, t[..., None]], axis=-1)
    bottom = xp.broadcast_to(xp.asarray([0.0, 0.0, 0.0, 1.0], dtype=c2w.dtype), c2w.shape[:-2] + (1, 4))
    return xp.concatenate([top, bottom], axis=-2)


def denormalize_poses(
    c2w: Float[ArrayLike, "... 4 4"], transform: Float[ArrayLike, "4 4"]
) -> Float[ArrayLike, "... 4 4"]:
    """Undo :func:`normalize_scene`: map normalised ``c2w`` back to the original world."""
    xp = _xp(c2w, transform)
    _check_trailing(c2w, (4, 4), "c2w", "4, 4")
    if tuple(transform.shape) != (4, 4):
        raise ValueError(f"transform: expected shape [4, 4], got {tuple(transform.shape)}")
    dtype = _float_dtype(c2w)
    transform = xp.asarray(transform, dtype=dtype)
    scale = xp.linalg.norm(transform[:3, 0])
    inv_rot = transform[:3, :3].T / (scale * scale)  # (s R)^-1 = R^T / s = (s R)^T / s^2
    inverse = xp.concatenate(
        [
            xp.concatenate([inv_rot, (-(inv_rot @ transform[:3, 3]))[:, None]], axis=1),
            xp.asarray([[0.0, 0.0, 0.0, 1.0]], dtype=dtype),
        ],
        axis=0,
    )
    return _apply_similarity(inverse, 1.0 / scale, xp.asarray(c2w, dtype=dtype), xp)


def validate_cameras(
    c2w: ArrayLike,
    intrinsics: ArrayLike,
    name: str = "cameras",
    frame_names: Sequence[str] | None = None,
    atol: float = 1e-4,
) -> None:
    """Raise ``ValueError`` unless the cameras are usable (host-side check, not jit-able).

    Checks: ``c2w`` is ``[N, 4, 4]`` and ``intrinsics`` ``[N, 4]``; every value finite;
    last row of ``c2w`` is ``(0, 0, 0, 1)``; rotation orthonormal (``|R^T R - I| <= atol``)
    with determinant +1; ``fx, fy > 0``. The message names ``name``, the frame (by
    ``frame_names[i]`` when given), the field and the expected shape or value.
    """
    c2w = np.asarray(c2w)
    intrinsics = np.asarray(intrinsics)
    if c2w.ndim != 3 or c2w.shape[1:] != (4, 4):
        raise UserError(f"{name}: c2w must have shape [N, 4, 4], got {c2w.shape}")
    n = c2w.shape[0]
    if intrinsics.shape != (n, 4):
        raise UserError(f"{name}: intrinsics must have shape [{n}, 4] (fx, fy, cx, cy), got {intrinsics.shape}")

    def frame(i: int) -> str:
        return f"{name}, frame {i}" + (f" ({frame_names[i]})" if frame_names is not None else "")

    for field, arr in (("c2w", c2w), ("intrinsics", intrinsics)):
        bad = ~np.isfinite(arr).reshape(n, -1).all(axis=1)
        if bad.any():
            i = int(np.argmax(bad))
            raise UserError(
                f"{frame(i)}: {field} has non-finite values: {arr[i].tolist()} "
                f"({int((~np.isfinite(arr)).sum())} non-finite value(s) in {int(bad.sum())} of {n} frames)"
            )
    c2w = c2w.astype(np.float64)
    bottom_err = np.abs(c2w[:, 3, :] - np.array([0.0, 0.0, 0.0, 1.0])).max(axis=1)
    rot = c2w[:, :3, :3]
    ortho_err = np.abs(np.einsum("nji,njk->nik", rot, rot) - np.eye(3)).max(axis=(1, 2))
    det = np.linalg.det(rot)
    for i in range(n):
        if bottom_err[i] > atol:
            raise UserError(f"{frame(i)}: c2w last row must be (0, 0, 0, 1), got {c2w[i, 3].tolist()}")
        if ortho_err[i] > atol or det[i] < 0:
            raise UserError(
                f"{frame(i)}: c2w[:3, :3] is not a rotation (max |R^T R - I| = {ortho_err[i]:.2e}, "
                f"det = {det[i]:.4f}; expected an orthonormal matrix with det +1, tolerance {atol})"
            )
    bad_focal = (intrinsics[:, :2] <= 0).any(axis=1)
    if bad_focal.any():
        i = int(np.argmax(bad_focal))
        raise UserError(
            f"{frame(i)}: intrinsics focal lengths must be > 0, got fx={intrinsics[i, 0]}, fy={intrinsics[i, 1]}"
        )


__all__ = [
    "crop_intrinsics",
    "denormalize_poses",
    "normalize_scene",
    "opencv_to_opengl",
    "opengl_to_opencv",
    "pixel_rays",
    "plucker",
    "project_points",
    "rays_through_pixels",
    "resize_intrinsics",
    "unproject_depth",
    "validate_cameras",
]
