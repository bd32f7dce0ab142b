"""Real captures from ../shared/data (never copied into the repo): the instant-ngp fox
(transforms.json, 17 of 67 images missing on purpose) and the beer can (COLMAP binary,
per-image SIMPLE_RADIAL). The COLMAP reprojection checks prove the conventions (pose
direction, pixel centres, distortion), not just the parsing."""

import json
import warnings

import numpy as np
import pytest

from llrmpp_jax.data.distortion import distort_pixels, undistort_pixels
from llrmpp_jax.data.formats import read_colmap_model, read_colmap_scene, read_nerfstudio_scene
from llrmpp_jax.data.resample import remap, resize_image
from llrmpp_jax.geometry import project_points, resize_intrinsics
from tests.helpers.environment import shared_path


@pytest.fixture(scope="module")
def beer():
    sparse = shared_path("data", "beer", "sparse", "0")
    scene = read_colmap_scene(sparse, shared_path("data", "beer", "images"))
    return scene, read_colmap_model(sparse)


def test_fox_loads_skipping_the_missing_images():
    root = shared_path("data", "fox")
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        s = read_nerfstudio_scene(root)
    msgs = [str(w.message) for w in caught]
    assert len(msgs) == 1 and "skipped 17 of 67 frames" in msgs[0], msgs
    assert len(s) == 50
    np.testing.assert_allclose(s.intrinsics[0], [1375.52, 1374.49, 554.558, 965.268])
    np.testing.assert_array_equal(s.hw[0], [1920, 1080])
    np.testing.assert_allclose(s.distortion[0], [0.0578421, -0.0805099, -0.000980296, 0.00015575, 0.0])  # pyright: ignore[reportOptionalSubscript] -- this capture has distortion
    meta = json.load(open(f"{root}/transforms.json"))
    first = np.array(meta["frames"][0]["transform_matrix"])
    assert meta["frames"][0]["file_path"].endswith("0001.jpg") and s.frame_names[0].endswith("0001.jpg")
    np.testing.assert_allclose(s.c2w[0], first @ np.diag([1.0, -1.0, -1.0, 1.0]), atol=1e-12)


def test_fox_cameras_look_at_a_common_point_in_front_of_them():
    """The least-squares point nearest all optical axes (the fox head) lies in front of
    every camera (OpenCV z > 0) and within a few pixels' worth of each axis; with the
    OpenGL axes left unflipped it would be behind them."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        s = read_nerfstudio_scene(shared_path("data", "fox"))
    o, d = s.c2w[:, :3, 3], s.c2w[:, :3, 2]
    proj = np.eye(3)[None] - d[:, :, None] * d[:, None, :]
    p = np.linalg.solve(proj.sum(0), np.einsum("nij,nj->i", proj, o))
    px, z = project_points(np.tile(p, (len(s), 1, 1)), s.c2w, s.intrinsics)
    assert (z > 0).all()
    centre = s.intrinsics[:, 2:]
    assert np.median(np.linalg.norm(px[:, 0] - centre, axis=1)) < 200  # px, in 1080x1920 frames


def test_fox_undistorts_after_resizing_like_before():
    """Undistorting at the resized size (the fast path) matches undistorting the full frame
    and then resizing, away from the border."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        s = read_nerfstudio_scene(shared_path("data", "fox"))
    small = s.image(3, (480, 270))
    full_then_small = resize_image(s.image(3), (480, 270))
    assert small.shape == (480, 270, 3) and 0 <= small.min() and small.max() <= 1
    assert np.abs(small - full_then_small)[10:-10, 10:-10].mean() < 0.01


def test_beer_colmap_reprojection(beer):
    """Each COLMAP 3D point, projected through our cameras: (a) its mean error over its
    track, measured in the distorted image, equals COLMAP's recorded error; (b) against
    the undistorted observation, the median error is below 1 px and 90% lie within 2 px."""
    scene, (cams, imgs, pts) = beer
    assert len(scene) == 71 and {c.model for c in cams.values()} == {"SIMPLE_RADIAL"} and len(pts) == 4414
    frame = {name.rsplit("/", 1)[-1]: i for i, name in enumerate(scene.frame_names)}
    rows = [
        (pi, frame[imgs[iid].name], iid, k)
        for pi, p in enumerate(pts.values())
        for iid, k in zip(p.image_ids, p.point2d_idxs)
    ]
    point_of, frame_of = np.array([r[0] for r in rows]), np.array([r[1] for r in rows])
    xyz = np.stack([p.xyz for p in pts.values()])[point_of]
    obs = np.stack([imgs[r[2]].xys[r[3]] for r in rows])
    errors, distorted_err = np.zeros(len(rows)), np.zeros(len(rows))
    for f in range(len(scene)):
        sel = frame_of == f
        px, z = project_points(xyz[sel], scene.c2w[f], scene.intrinsics[f])
        assert (z > 0).all()
        k, dist = scene.intrinsics[f], scene.distortion[f]
        errors[sel] = np.linalg.norm(px - undistort_pixels(obs[sel], k, dist), axis=1)
        distorted_err[sel] = np.linalg.norm(distort_pixels(px, k, dist) - obs[sel], axis=1)  # pyright: ignore[reportArgumentType] -- NumPy arrays
    mine = np.bincount(point_of, distorted_err) / np.bincount(point_of)
    np.testing.assert_allclose(mine, [p.error for p in pts.values()], atol=1e-6)
    assert np.median(errors) < 1.0 and (errors < 2.0).mean() > 0.9, (np.median(errors), (errors < 2).mean())


def test_beer_point_colours_match_the_undistorted_images(beer):
    """Sampling our (undistorted, resized) images at the projected points gives the
    points' recorded colours; using a neighbouring frame's camera instead does not."""
    scene, (cams, imgs, pts) = beer
    by_name = {im.name: im for im in imgs.values()}
    hw = (320, 180)
    right, wrong = [], []
    for f in (5, 35, 65):
        img = scene.image(f, hw)
        k = resize_intrinsics(scene.intrinsics[f], tuple(scene.hw[f]), hw)
        ids = by_name[scene.frame_names[f].rsplit("/", 1)[-1]].point3d_ids
        ids = ids[ids >= 0]
        xyz = np.stack([pts[i].xyz for i in ids])
        rgb = np.stack([pts[i].rgb for i in ids]) / 255.0
        px, _ = project_points(xyz, scene.c2w[f], k)
        right.append(np.abs(remap(img, px[None].astype(np.float32))[0] - rgb).mean(axis=1))  # pyright: ignore[reportArgumentType] -- a jax.Array where a NumPy array is annotated: both work
        px, _ = project_points(xyz, scene.c2w[f + 3], k)
        wrong.append(np.abs(remap(img, px[None].astype(np.float32))[0] - rgb).mean(axis=1))  # pyright: ignore[reportArgumentType] -- a jax.Array where a NumPy array is annotated: both work
    right, wrong = np.median(np.concatenate(right)), np.median(np.concatenate(wrong))
    assert right < 0.06 and right < 0.6 * wrong, (right, wrong)
