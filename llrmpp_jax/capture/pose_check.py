"""Checks of camera poses from photos: is a COLMAP model folded, and how close is it to a
reference.

**Folds.** A scene with a symmetric object or a repeating texture (a can whose label repeats
every half turn, floor tiles) gives SIFT many verified matches between views from *different*
sides. Incremental (and global) mapping can then register a run of frames on the wrong side:
the model is self-consistent and its reprojection error low, but that run is rotated by up to
180 degrees. Such a model breaks somewhere along the capture: two photos taken one after the
other (their names sort in capture order, as a phone's and a video's frames do) are strongly
matched in COLMAP's database, yet the model puts them apart, so they share almost no 3D point.
:func:`continuity_breaks` lists these pairs. Photos whose names are not in capture order are
rarely strongly matched neighbours, so the check stays silent there (it can miss a fold, it
does not invent one).

**Agreement with a reference** (:func:`compare_poses`): a similarity aligns the estimate to
the reference. RANSAC over Umeyama fits of the camera centres (scikit-image) finds the frames
that agree; on those, the rotation is the mean of the per-frame orientation differences and
the scale and translation the least-squares fit of the centres. Then per frame: the angle of
the rotation difference, and the centre distance as a fraction of the reference cameras'
extent (the diagonal of their centres' bounding box).
"""

from __future__ import annotations

import contextlib
from dataclasses import dataclass

import numpy as np

# (rotation camera -> world [3, 3], camera centre in world [3]) per image name.
Poses = dict[str, tuple[np.ndarray, np.ndarray]]


def camera_poses(reconstruction) -> Poses:
    """Registered images of a ``pycolmap.Reconstruction`` as ``{name: (R_c2w, centre)}``."""
    out: Poses = {}
    for image_id in reconstruction.reg_image_ids():
        image = reconstruction.image(image_id)
        cam_from_world = image.cam_from_world()
        rotation = np.asarray(cam_from_world.rotation.matrix(), np.float64)
        translation = np.asarray(cam_from_world.translation, np.float64)
        out[image.name] = (rotation.T, -rotation.T @ translation)
    return out


@dataclass(frozen=True)
class Break:
    """Two consecutive photos strongly matched in the database but apart in the model."""

    first: str
    second: str
    inliers: int  # verified matches between them (COLMAP's two-view geometry)
    shared_points: int  # 3D points of the model both images observe

    def __str__(self) -> str:
        return f"{self.first}/{self.second} ({self.inliers} matches, {self.shared_points} shared points)"


def continuity_breaks(
    reconstruction, database: str, min_inliers: int = 50, max_shared_fraction: float = 0.1
) -> list[Break]:
    """Consecutive registered images (by name) with at least ``min_inliers`` verified matches in
    ``database`` whose model shares fewer than ``max_shared_fraction`` of that many 3D points.

    A fold (module docstring) shows as such a pair; a cut in the capture does not (its two
    photos do not match). The shipped COLMAP model of this project's beer capture has three.
    """
    import pycolmap

    by_name = {reconstruction.image(i).name: i for i in reconstruction.reg_image_ids()}
    with contextlib.closing(pycolmap.Database.open(database)) as db:
        pair_ids, counts = db.read_two_view_geometry_num_inliers()
        db_ids = {image.name: image.image_id for image in db.read_all_images()}
    inliers = dict(zip(pair_ids, counts))
    points = {
        name: {p.point3D_id for p in reconstruction.image(i).points2D if p.has_point3D()} for name, i in by_name.items()
    }
    names = sorted(by_name)
    breaks = []
    for a, b in zip(names, names[1:]):
        if a not in db_ids or b not in db_ids:
            continue
        n = int(inliers.get(pycolmap.image_pair_to_pair_id(db_ids[a], db_ids[b]), 0))
        shared = len(points[a] & points[b])
        if n >= min_inliers and shared < max_shared_fraction * n:
            breaks.append(Break(a, b, n, shared))
    return breaks


@dataclass(frozen=True)
class PoseAgreement:
    """:func:`compare_poses`' result; arrays are per common image, in ``names`` order."""

    names: tuple[str, ...]
    rotation_error_deg: np.ndarray
    position_error: np.ndarray  # centre distance / reference extent
    within: np.ndarray  # bool: both errors within the tolerances
    scale: float  # reference units per estimate unit
    rotation_tol_deg: float
    position_tol: float

    @property
    def fraction_within(self) -> float:
        return float(np.mean(self.within)) if len(self.names) else 0.0

    def summary(self) -> dict:
        """JSON-ready numbers: counts, fraction within, medians, the frames outside."""
        return {
            "frames": len(self.names),
            "within": int(np.sum(self.within)),
            "fraction_within": self.fraction_within,
            "rotation_tol_deg": self.rotation_tol_deg,
            "position_tol": self.position_tol,
            "median_rotation_error_deg": float(np.median(self.rotation_error_deg)),
            "median_position_error": float(np.median(self.position_error)),
            "max_rotation_error_deg": float(np.max(self.rotation_error_deg)),
            "outside": [n for n, ok in zip(self.names, self.within) if not ok],
        }


def rotation_angle_deg(rotation: np.ndarray) -> float:
    """Angle (degrees) of a 3x3 rotation matrix."""
    return float(np.degrees(np.arccos(np.clip((np.trace(rotation) - 1.0) / 2.0, -1.0, 1.0))))


def compare_poses(
    estimate: Poses, reference: Poses, rotation_tol_deg: float = 2.0, position_tol: float = 0.02, seed: int = 0
) -> PoseAgreement:
    """Align ``estimate`` to ``reference`` by a similarity (module docstring; RANSAC inlier
    threshold ``position_tol`` of the reference extent) and measure each common image's
    rotation and position error."""
    from skimage.measure import ransac
    from skimage.transform import SimilarityTransform

    names = tuple(sorted(set(estimate) & set(reference)))
    if len(names) < 3:
        raise ValueError(f"compare_poses needs >= 3 common images, got {len(names)}")
    src = np.array([estimate[n][1] for n in names])
    dst = np.array([reference[n][1] for n in names])
    extent = float(np.linalg.norm(dst.max(0) - dst.min(0)))
    _, inliers = ransac(
        (src, dst),
        SimilarityTransform,
        min_samples=3,
        residual_threshold=position_tol * extent,
        max_trials=2000,
        rng=seed,
    )
    inliers = np.ones(len(names), bool) if inliers is None or inliers.sum() < 3 else inliers  # pyright: ignore[reportAttributeAccessIssue] -- ransac's inliers: a bool array or None

    def fit(use: np.ndarray) -> tuple[np.ndarray, np.ndarray, float]:
        """Rotation errors (degrees), position errors (fractions) of every frame and the scale of
        the similarity fitted to the frames in ``use``."""
        u, _, vt = np.linalg.svd(sum(reference[n][0] @ estimate[n][0].T for n, ok in zip(names, use) if ok))
        rotation = u @ np.diag([1.0, 1.0, np.linalg.det(u @ vt)]) @ vt
        s_mean, d_mean = src[use].mean(0), dst[use].mean(0)
        turned = (src[use] - s_mean) @ rotation.T
        scale = float(np.sum(turned * (dst[use] - d_mean)) / np.sum(turned * turned))
        position = np.linalg.norm(scale * (src - s_mean) @ rotation.T + d_mean - dst, axis=1) / extent
        angles = np.array([rotation_angle_deg(reference[n][0].T @ rotation @ estimate[n][0]) for n in names])
        return angles, position, scale

    # The alignment's rotation from the inliers' orientations (chordal mean of R_ref R_est^T):
    # the centres of a short arc of cameras pin it down only loosely. Then scale and
    # translation by least squares of their centres given that rotation. A second fit leaves
    # out the frames whose orientation is off by more than the tolerance.
    angles, position, scale = fit(inliers)  # pyright: ignore[reportArgumentType] -- as above
    agreeing = inliers & (angles <= rotation_tol_deg)
    if agreeing.sum() >= 3:
        angles, position, scale = fit(agreeing)
    within = (angles <= rotation_tol_deg) & (position <= position_tol)
    return PoseAgreement(names, angles, position, within, scale, rotation_tol_deg, position_tol)
