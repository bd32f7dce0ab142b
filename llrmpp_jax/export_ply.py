"""Gaussians <-> PLY files: the standard 3D Gaussian Splatting layout (colour mode) and ours (feature mode).

One ``vertex`` element, one vertex per Gaussian, every property little-endian float32, in
this order (the order and names of the original 3DGS ``save_ply``, so common viewers load
colour-mode files):

============================  ===============================================================
``x y z``                     centre, in the capture's world frame
``nx ny nz``                  zeros (3DGS writes them; nothing reads them)
``f_dc_0..2``                 colour mode: SH coefficient 0 of R, G, B
``f_rest_0..3(M-1)-1``        colour mode: SH coefficients 1..M-1 (M = (deg+1)^2), channel-major:
                              ``f_rest_{c*(M-1) + k-1}`` = coefficient k of channel c
``f_feat_0..F-1``             feature mode: the Gaussian's feature (view-independent)
``partition_0..S-1``          feature mode: partition logits, ``features @ W_partition``; the
                              opacity of copy s is ``opacity * softmax(logits)_s``
``opacity``                   ``logit(opacity)``, opacity clipped to ``[2^-24, 1 - 2^-24]``
``scale_0..2``                ``log(scale)`` in world units; 2D Gaussians (``primitive="2dgs"``)
                              as flat 3D ones: ``scale_2`` is ``log`` of
                              ``gaussians.SURFEL_THICKNESS`` x the smaller tangent scale (the
                              standard 3DGS layout, which common viewers read; the 2DGS
                              paper's own files drop ``scale_2``, which those viewers cannot)
``rot_0..3``                  unit quaternion ``(w, x, y, z)``, Gaussian-to-world rotation
============================  ===============================================================

Colour convention. Our colour mode is gsplat's, which is 3DGS's: the same real SH basis
(``splat/sh.py``), ``RGB = max(SH(d) . coeffs + 0.5, 0)`` with ``d`` the direction from the
camera centre to the mean, so ``f_dc`` is our coefficient 0 unchanged (a viewer's
``0.5 + C0 * f_dc`` is our degree-0 colour). Our flattened features are coefficient-major,
RGB fastest (``gaussians.Gaussians``); the PLY is channel-major, hence the reorder.

World frame. The model works in the normalised scene frame (``geometry.normalize_scene``);
``world_from_scene`` is the 4x4 similarity ``[[s R, t], [0, 1]]`` back to the capture's
frame (``s > 0``, ``R`` a proper rotation). Means map by it, quaternions are composed
with ``R`` (``q_world = q_R * q``), scales multiply by ``s``, and SH coefficients of degree
>= 1 are rotated (view directions rotate with the world; :func:`sh_rotation`). Feature-mode
files keep the features as predicted: rendering them needs our decoder, whose input rays
live in the scene frame, so the file's header records ``world_from_scene`` (a comment) to
map cameras back.

The header also carries ``comment llrmpp-jax mode=<color|feature>``. :func:`read_ply`
reads our files and standard 3DGS files (no comments; mode from the fields).
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
import plyfile

from llrmpp_jax.array_typing import ArrayLike, Float
from llrmpp_jax.config import ModelConfig
from llrmpp_jax.errors import UserError
from llrmpp_jax.file_kinds import check_ply
from llrmpp_jax.finite import check_finite
from llrmpp_jax.gaussians import OPACITY_LOGIT_EPS, Gaussians, surfel_scales_3d
from llrmpp_jax.splat.sh import num_sh_bases, sh_basis

_TAG = "llrmpp-jax"
_GEOMETRY = ["x", "y", "z", "nx", "ny", "nz"]
_SIMILARITY_TOL = 1e-5
_DIRECTIONS = 64  # fitting directions for sh_rotation (>= 2 * 3 + 1 per degree, well spread)


class PlyGaussians(NamedTuple):
    """What :func:`read_ply` returns: unbatched Gaussians (float32 NumPy, world frame,
    decoded: linear scales, opacities in (0, 1), unit quaternions, features in
    :class:`~llrmpp_jax.gaussians.Gaussians`' layout) and the file's extras."""

    gaussians: Gaussians
    mode: str  # "color" | "feature"
    partition_logits: Float[np.ndarray, "N S"] | None  # feature mode
    world_from_scene: Float[np.ndarray, "4 4"] | None  # None in files without our header


def standard_fields(sh_degree: int) -> list[str]:
    """The 3DGS vertex properties, in file order, for SH of degree ``sh_degree``."""
    rest = 3 * (num_sh_bases(sh_degree) - 1)
    return _GEOMETRY + [f"f_dc_{i}" for i in range(3)] + [f"f_rest_{i}" for i in range(rest)] + _tail_fields()


def feature_fields(feature_dim: int, partitions: int) -> list[str]:
    """Our feature-mode vertex properties, in file order."""
    return (
        _GEOMETRY
        + [f"f_feat_{i}" for i in range(feature_dim)]
        + [f"partition_{i}" for i in range(partitions)]
        + _tail_fields()
    )


def _tail_fields() -> list[str]:
    return ["opacity"] + [f"scale_{i}" for i in range(3)] + [f"rot_{i}" for i in range(4)]


def split_similarity(world_from_scene: Float[np.ndarray, "4 4"]) -> tuple[float, np.ndarray, np.ndarray]:
    """``(s, R, t)`` of a similarity ``[[s R, t], [0, 1]]``; ValueError if it is not one."""
    m = np.asarray(world_from_scene, np.float64)
    if m.shape != (4, 4) or not np.all(np.isfinite(m)):
        raise UserError(f"world_from_scene must be a finite 4x4 matrix, got shape {m.shape}")
    if not np.allclose(m[3], [0, 0, 0, 1], atol=_SIMILARITY_TOL):
        raise UserError(f"world_from_scene: last row must be [0, 0, 0, 1], got {m[3].tolist()}")
    det = np.linalg.det(m[:3, :3])
    if det <= 0:
        raise UserError(
            f"world_from_scene: the 3x3 part has determinant {det:.3g}; need a rotation "
            "times a positive scale (reflections cannot be expressed by quaternions)"
        )
    s = float(np.cbrt(det))
    rot = m[:3, :3] / s
    err = float(np.max(np.abs(rot.T @ rot - np.eye(3))))
    if err > _SIMILARITY_TOL:
        raise UserError(f"world_from_scene is not rotation x uniform scale: |R^T R - I| = {err:.3g}")
    return s, rot, m[:3, 3]


def rotmat_to_qvec(rot: Float[np.ndarray, "3 3"]) -> Float[np.ndarray, " 4"]:
    """Unit quaternion ``(w, x, y, z)`` with ``w >= 0`` of a rotation matrix (the dominant
    eigenvector of Bar-Itzhack's symmetric 4x4 matrix, as COLMAP's scripts compute it)."""
    r = np.asarray(rot, dtype=np.float64)
    k = (
        np.array(
            [
                [r[0, 0] - r[1, 1] - r[2, 2], 0, 0, 0],
                [r[1, 0] + r[0, 1], r[1, 1] - r[0, 0] - r[2, 2], 0, 0],
                [r[2, 0] + r[0, 2], r[2, 1] + r[1, 2], r[2, 2] - r[0, 0] - r[1, 1], 0],
                [r[2, 1] - r[1, 2], r[0, 2] - r[2, 0], r[1, 0] - r[0, 1], r[0, 0] + r[1, 1] + r[2, 2]],
            ]
        )
        / 3.0
    )
    vals, vecs = np.linalg.eigh(k)
    q = vecs[[3, 0, 1, 2], np.argmax(vals)]
    return q if q[0] >= 0 else -q


def quat_multiply(
    a: Float[np.ndarray, "*#batch 4"], b: Float[np.ndarray, "*#batch 4"]
) -> Float[np.ndarray, "*batch 4"]:
    """Hamilton product ``a * b`` of ``(w, x, y, z)`` quaternions (rotation ``a`` after ``b``;
    the leading axes broadcast)."""
    aw, ax, ay, az = np.moveaxis(a, -1, 0)
    bw, bx, by, bz = np.moveaxis(b, -1, 0)
    return np.stack(
        [
            aw * bw - ax * bx - ay * by - az * bz,
            aw * bx + ax * bw + ay * bz - az * by,
            aw * by - ax * bz + ay * bw + az * bx,
            aw * bz + ax * by - ay * bx + az * bw,
        ],
        axis=-1,
    )


def sh_rotation(rot: Float[np.ndarray, "3 3"], degree: int) -> Float[np.ndarray, "bases bases"]:
    """``X`` [bases, bases] with ``SH_world(R d) . (X c) == SH_scene(d) . c`` for every direction d.

    Each degree's real SH span is closed under rotation, so ``Y(R^T d) = A Y(d)`` for a
    block-diagonal ``A`` and ``X = A^T``; it is fitted in float64 by least squares over
    well-spread directions (exact up to rounding: the system is consistent and, with
    more directions than coefficients, of full rank).
    """
    n = np.arange(_DIRECTIONS) + 0.5  # Fibonacci sphere
    z = 1.0 - 2.0 * n / _DIRECTIONS
    phi = np.pi * (1.0 + 5.0**0.5) * n
    dirs = np.stack([np.sqrt(1 - z * z) * np.cos(phi), np.sqrt(1 - z * z) * np.sin(phi), z], axis=-1)
    with jax.enable_x64(True):
        basis = np.asarray(sh_basis(jnp.asarray(dirs, jnp.float64), degree))
        rotated = np.asarray(sh_basis(jnp.asarray(dirs @ np.asarray(rot, np.float64), jnp.float64), degree))
    return np.linalg.lstsq(basis, rotated, rcond=None)[0]  # rows of dirs @ R are R^T d


def _unbatched(gaussians: Gaussians) -> Gaussians:
    g = Gaussians(*(np.asarray(a) for a in gaussians))  # pyright: ignore[reportArgumentType] -- a NumPy array where jax.Array is annotated: both work
    if g.means.ndim == 3:
        if g.means.shape[0] != 1:
            raise UserError(f"export_ply writes one scene; got a batch of {g.means.shape[0]} (means {g.means.shape})")
        g = Gaussians(*(a[0] for a in g))
    n = g.means.shape[0]
    want = {"means": (n, 3), "quats": (n, 4), "scales": (n, 3), "opacities": (n,)}
    for name, shape in want.items():
        if getattr(g, name).shape != shape:
            raise UserError(
                f"Gaussians.{name}: expected shape {shape} (or with a batch of 1), got {getattr(g, name).shape}"
            )
    if g.features.ndim != 2 or g.features.shape[0] != n:
        raise UserError(f"Gaussians.features: expected shape ({n}, F), got {g.features.shape}")
    for name, a in zip(Gaussians._fields, g, strict=True):
        bad = int(np.sum(~np.all(np.isfinite(a.reshape(n, -1)), axis=-1)))
        if bad:
            raise UserError(f"Gaussians.{name}: {bad} of {n} Gaussians have non-finite values")
    return g


def ply_fields(
    gaussians: Gaussians,
    cfg: ModelConfig,
    world_from_scene: Float[np.ndarray, "4 4"],
    partition_logits: Float[ArrayLike, "N S"] | Float[ArrayLike, "1 N S"] | None = None,
) -> dict[str, Float[np.ndarray, " N"]]:
    """The PLY's columns (name -> float32 ``[N]``, file order; module docstring).

    Args:
      gaussians: one scene's Gaussians in the normalised scene frame, ``[N, ...]`` or with
        a batch axis of 1 (``[1, N, ...]``, as ``model.reconstruct`` returns for one scene).
      cfg: the model's config (mode, SH degree, F, S).
      world_from_scene: 4x4 similarity, scene frame -> capture's world frame.
      partition_logits: feature mode only, required: ``model.partition_logits(params, cfg, g)``.
    """
    if cfg.head.primitive == "2dgs":  # 2D Gaussians as flat 3D ones (module docstring)
        gaussians = gaussians._replace(scales=surfel_scales_3d(gaussians.scales))
    g = _unbatched(gaussians)
    n = g.means.shape[0]
    s, rot, t = split_similarity(world_from_scene)
    f64 = lambda a: np.asarray(a, np.float64)  # noqa: E731
    means = f64(g.means) @ rot.T * s + t
    quats = quat_multiply(rotmat_to_qvec(rot)[None], f64(g.quats))
    quats = quats / np.linalg.norm(quats, axis=-1, keepdims=True)
    opac = np.clip(f64(g.opacities), OPACITY_LOGIT_EPS, 1.0 - OPACITY_LOGIT_EPS)
    cols = {
        "x": means[:, 0],
        "y": means[:, 1],
        "z": means[:, 2],
        "nx": np.zeros(n),
        "ny": np.zeros(n),
        "nz": np.zeros(n),
    }
    if cfg.head.mode == "color":
        m = num_sh_bases(cfg.head.sh_degree)
        if g.features.shape[1] != 3 * m:
            raise UserError(
                f"Gaussians.features: colour mode with sh_degree {cfg.head.sh_degree} needs "
                f"{3 * m} SH values per Gaussian, got {g.features.shape[1]}"
            )
        sh = np.einsum("km,nmc->nkc", sh_rotation(rot, cfg.head.sh_degree), f64(g.features).reshape(n, m, 3))
        cols.update({f"f_dc_{c}": sh[:, 0, c] for c in range(3)})
        rest = sh[:, 1:, :].transpose(0, 2, 1).reshape(n, -1)  # channel-major
        cols.update({f"f_rest_{i}": rest[:, i] for i in range(rest.shape[1])})
    else:
        if partition_logits is None:
            raise UserError(
                "export_ply: feature mode needs partition_logits (model.partition_logits(params, cfg, gaussians))"
            )
        logits = np.asarray(partition_logits).reshape(-1, np.shape(partition_logits)[-1])
        if logits.shape != (n, cfg.decoder.partitions):
            raise UserError(
                f"partition_logits: expected shape ({n}, {cfg.decoder.partitions}), got {np.shape(partition_logits)}"
            )
        cols.update({f"f_feat_{i}": g.features[:, i] for i in range(g.features.shape[1])})
        cols.update({f"partition_{i}": logits[:, i] for i in range(logits.shape[1])})
    cols["opacity"] = np.log(opac) - np.log1p(-opac)
    log_scales = np.log(f64(g.scales) * s)
    cols.update({f"scale_{i}": log_scales[:, i] for i in range(3)})
    cols.update({f"rot_{i}": quats[:, i] for i in range(4)})
    return {k: v.astype(np.float32) for k, v in cols.items()}


def export_ply(
    path: str,
    gaussians: Gaussians,
    cfg: ModelConfig,
    world_from_scene: Float[np.ndarray, "4 4"],
    partition_logits: Float[ArrayLike, "N S"] | Float[ArrayLike, "1 N S"] | None = None,
) -> int:
    """Write one scene's Gaussians as a binary little-endian PLY (:func:`ply_fields`).

    Returns the number of Gaussians written.
    """
    cols = ply_fields(gaussians, cfg, world_from_scene, partition_logits)
    n = len(cols["x"])
    vertex = np.empty(n, dtype=[(k, "<f4") for k in cols])
    for k, v in cols.items():
        vertex[k] = v
    wfs = " ".join(repr(float(x)) for x in np.asarray(world_from_scene, np.float64).reshape(-1))
    comments = [f"{_TAG} mode={cfg.head.mode}", f"{_TAG} world_from_scene {wfs}"]
    plyfile.PlyData([plyfile.PlyElement.describe(vertex, "vertex")], byte_order="<", comments=comments).write(path)
    return n


def _header(comments: list[str]) -> tuple[str | None, np.ndarray | None]:
    mode, wfs = None, None
    for c in comments:
        parts = c.split()
        if len(parts) == 2 and parts[0] == _TAG and parts[1].startswith("mode="):
            mode = parts[1][len("mode=") :]
        elif len(parts) == 18 and parts[:2] == [_TAG, "world_from_scene"]:
            wfs = np.array([float(x) for x in parts[2:]]).reshape(4, 4)
    return mode, wfs


def read_ply(path: str) -> PlyGaussians:
    """Read a PLY written by :func:`export_ply` or a standard 3DGS PLY (module docstring).

    Raises ``UserError`` (a ``ValueError``) naming the file: not a PLY (what it looks like),
    a header or body plyfile cannot parse, the first missing property, or the first property
    holding NaN or infinity (and how many values do).
    """
    check_ply(path)
    try:
        data = plyfile.PlyData.read(path)
    except (plyfile.PlyParseError, ValueError, EOFError, OSError) as e:
        raise UserError(f"{path}: truncated or corrupt PLY file ({type(e).__name__}: {e})") from None
    if "vertex" not in data:
        raise UserError(f"{path}: no 'vertex' element")
    v = data["vertex"].data
    names = set(v.dtype.names)
    try:
        header_mode, wfs = _header(list(data.comments))
    except ValueError as e:  # a world_from_scene comment that is not 16 numbers
        raise UserError(f"{path}: damaged llrmpp comment in the PLY header ({e})") from None
    mode = header_mode or ("color" if "f_dc_0" in names else "feature")
    if mode == "color":
        n_rest = sum(1 for k in names if k.startswith("f_rest_"))
        m = 1 + n_rest // 3
        want = standard_fields(round(m**0.5) - 1)
    else:
        f = sum(1 for k in names if k.startswith("f_feat_"))
        s = sum(1 for k in names if k.startswith("partition_"))
        want = feature_fields(f, s)
    missing = [k for k in want if k not in names]
    if missing:
        raise UserError(f"{path}: {mode}-mode PLY lacks property {missing[0]!r} ({len(missing)} missing)")
    check_finite(path, {k: v[k] for k in want}, "property ")
    col = lambda *ks: np.stack([np.asarray(v[k], np.float32) for k in ks], axis=-1)  # noqa: E731
    n = len(v)
    if mode == "color":
        rest = col(*(f"f_rest_{i}" for i in range(3 * (m - 1)))).reshape(n, 3, m - 1).transpose(0, 2, 1)
        features = np.concatenate([col("f_dc_0", "f_dc_1", "f_dc_2")[:, None, :], rest], axis=1).reshape(n, -1)
        logits = None
    else:
        features = col(*(f"f_feat_{i}" for i in range(f)))
        logits = col(*(f"partition_{i}" for i in range(s)))
    quats = col("rot_0", "rot_1", "rot_2", "rot_3")
    g = Gaussians(
        means=col("x", "y", "z"),  # pyright: ignore[reportArgumentType] -- a NumPy array where jax.Array is annotated: both work
        quats=quats / np.linalg.norm(quats, axis=-1, keepdims=True),
        scales=np.exp(col("scale_0", "scale_1", "scale_2")),  # pyright: ignore[reportArgumentType] -- a NumPy array where jax.Array is annotated: both work
        opacities=(1.0 / (1.0 + np.exp(-col("opacity")[:, 0]))).astype(np.float32),  # pyright: ignore[reportArgumentType] -- a NumPy array where jax.Array is annotated: both work
        features=features,  # pyright: ignore[reportArgumentType] -- a NumPy array where jax.Array is annotated: both work
    )
    return PlyGaussians(g, mode, logits, wfs)
