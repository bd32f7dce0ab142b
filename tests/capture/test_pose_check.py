"""Pose checks (``llrmpp_jax.capture.pose_check``): the similarity alignment against a known
transform, and the fold check on the beer capture, whose shipped COLMAP model is folded
between photos 0013 and 0014 while our sequential matching is not; a seeded run repeats
exactly."""

from __future__ import annotations

import os
import zlib

import numpy as np
import pycolmap
import pytest
from scipy.spatial.transform import Rotation

from llrmpp_jax.capture.pose_check import camera_poses, compare_poses, continuity_breaks, rotation_angle_deg
from llrmpp_jax.capture.poses import PosesConfig, estimate_poses
from llrmpp_jax.data.image_io import read_image, write_image
from llrmpp_jax.data.resample import resize_image
from tests.helpers.environment import shared_path


def test_compare_poses_recovers_a_similarity_and_flags_the_perturbed_frames(request):
    rng = np.random.default_rng(zlib.crc32(request.node.nodeid.encode()))
    n = 24
    reference = {
        f"{i:04d}.jpg": (Rotation.random(random_state=rng).as_matrix(), rng.normal(size=3) * 3.0)  # pyright: ignore[reportCallIssue] -- scipy still takes random_state; its stubs name only rng
        for i in range(n)
    }
    # The estimate lives in another frame: world_est = (world_ref - t) R / s.
    s, r, t = 0.37, Rotation.random(random_state=rng).as_matrix(), rng.normal(size=3)  # pyright: ignore[reportCallIssue] -- scipy still takes random_state; its stubs name only rng
    estimate = {k: (r.T @ rot, (centre - t) @ r / s) for k, (rot, centre) in reference.items()}
    names = sorted(reference)
    turned, moved = names[:3], names[3:5]
    for k in turned:  # 5 degrees about a random axis: outside the 2 degree tolerance
        axis = rng.normal(size=3)
        estimate[k] = (
            Rotation.from_rotvec(np.radians(5.0) * axis / np.linalg.norm(axis)).as_matrix() @ estimate[k][0],
            estimate[k][1],
        )
    for k in moved:  # half the camera extent away
        estimate[k] = (estimate[k][0], estimate[k][1] + 20.0)
    agreement = compare_poses(estimate, reference)
    assert agreement.scale == pytest.approx(s, rel=1e-9)
    assert set(agreement.summary()["outside"]) == set(turned + moved)
    errors = dict(zip(agreement.names, agreement.rotation_error_deg))
    np.testing.assert_allclose([errors[k] for k in turned], 5.0, atol=1e-6)
    kept = [k for k in names if k not in turned + moved]
    np.testing.assert_allclose([errors[k] for k in kept], 0.0, atol=1e-4)
    assert rotation_angle_deg(Rotation.from_rotvec([0.0, 0.0, np.pi / 3]).as_matrix()) == pytest.approx(60.0)


FRAMES = [f"{i:04d}.jpg" for i in range(8, 20)]  # the shipped model folds between 0013 and 0014


def test_beer_fold_is_found_in_the_shipped_model_and_absent_from_sequential_matching(tmp_path):
    capture = shared_path("data", "beer")
    photos = tmp_path / "photos"
    photos.mkdir()
    for name in FRAMES:
        image = read_image(os.path.join(capture, "images", name))
        write_image(str(photos / name), resize_image(image, (640, 360)))
    out = str(tmp_path / "capture")
    # Seeded: one thread, so COLMAP's RANSAC and mapping repeat exactly.
    report = estimate_poses(
        str(photos), out, PosesConfig(matcher="sequential", max_image_size=640, seed=0), progress=lambda s: None
    )
    assert report.registered == len(FRAMES) and report.breaks == () and report.seed == 0
    ours = camera_poses(pycolmap.Reconstruction(os.path.join(out, "sparse", "0")))

    shipped_model = pycolmap.Reconstruction(os.path.join(capture, "sparse", "0"))
    breaks = continuity_breaks(shipped_model, os.path.join(out, "database.db"))
    # 0007/0008 and 0019/0020 have no matches in our database (not our frames), so they are not checked.
    assert [(b.first, b.second) for b in breaks] == [("0013.jpg", "0014.jpg")]
    assert breaks[0].inliers >= 50 and breaks[0].shared_points < 5
    shipped = camera_poses(shipped_model)
    # Against all of the shipped frames at once, one side of the fold disagrees...
    assert compare_poses(ours, {k: shipped[k] for k in FRAMES}).fraction_within < 0.75
    # ...while each unbroken run of the shipped model agrees with ours (5 degrees, 10% of the
    # run's extent: these photos are 640 px high, the shipped model used 1280). With all cores,
    # COLMAP's result varies from run to run: 2 of 8 test runs here and 1 of 3 CI runs had
    # frames of the second run beyond the tolerances, once 5 of its 6. Hence one thread and a
    # seed above. A fold puts frames ~170 degrees off, so the bound also allows one frame out
    # and asks for a median under 2 degrees.
    for run in (FRAMES[:6], FRAMES[6:]):
        agreement = compare_poses(ours, {k: shipped[k] for k in run}, rotation_tol_deg=5.0, position_tol=0.1)
        assert agreement.within.sum() >= len(run) - 1, agreement.summary()
        assert np.median(agreement.rotation_error_deg) < 2.0, agreement.summary()


def test_a_seeded_run_repeats_exactly(tmp_path):
    """``PosesConfig(seed=...)``: three runs on the same photos give the same poses to the bit,
    and the seed is reported. (Unseeded on two threads, the third of three runs here once
    moved a camera centre by 0.06 model units.)"""
    photos = tmp_path / "photos"
    photos.mkdir()
    for name in FRAMES[:8]:
        image = read_image(os.path.join(shared_path("data", "beer"), "images", name))
        write_image(str(photos / name), resize_image(image, (320, 180)))
    poses = []
    for run in range(3):
        out = str(tmp_path / f"capture{run}")
        report = estimate_poses(
            str(photos), out, PosesConfig(matcher="sequential", max_image_size=320, seed=7), progress=lambda s: None
        )
        assert report.seed == 7 and report.registered >= 6, report
        poses.append(camera_poses(pycolmap.Reconstruction(os.path.join(out, "sparse", "0"))))
    for other in poses[1:]:
        assert sorted(other) == sorted(poses[0])
        for name in poses[0]:
            for a, b in zip(poses[0][name], other[name]):  # rotation, centre
                np.testing.assert_array_equal(a, b)
