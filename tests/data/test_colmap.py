"""COLMAP models (llrmpp_jax/data/formats/colmap.py) written by pycolmap itself, as text and
binary, from random cameras of every supported model, random poses, observations and
points; read back and compared with the values they were built from. Oracles: the
pinhole + OpenCV form of each model written out here, and c2w = [R^T | -R^T t] of the
world-to-camera (R, t) given to COLMAP. Then each kind of damaged model is one line
naming the file."""

import os

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from llrmpp_jax.data.formats import read_colmap_model, read_colmap_scene
from llrmpp_jax.data.formats.colmap import import_pycolmap
from llrmpp_jax.data.image_io import write_image
from llrmpp_jax.errors import MissingInputError

pycolmap = import_pycolmap()
MODELS = ("SIMPLE_PINHOLE", "PINHOLE", "SIMPLE_RADIAL", "RADIAL", "OPENCV")
TOL = 1e-12  # text: COLMAP writes 17 significant digits; c2w also goes through a quaternion


def _camera(rng, model):
    """COLMAP params of ``model`` and the (fx, fy, cx, cy), (k1, k2, p1, p2, k3) they mean."""
    f, g = rng.uniform(40.0, 80.0, 2)
    cx, cy = rng.uniform(20.0, 40.0, 2)
    k1, k2, p1, p2 = rng.uniform(-0.1, 0.1, 4)
    return {
        "SIMPLE_PINHOLE": ([f, cx, cy], [f, f, cx, cy], [0, 0, 0, 0, 0]),
        "PINHOLE": ([f, g, cx, cy], [f, g, cx, cy], [0, 0, 0, 0, 0]),
        "SIMPLE_RADIAL": ([f, cx, cy, k1], [f, f, cx, cy], [k1, 0, 0, 0, 0]),
        "RADIAL": ([f, cx, cy, k1, k2], [f, f, cx, cy], [k1, k2, 0, 0, 0]),
        "OPENCV": ([f, g, cx, cy, k1, k2, p1, p2], [f, g, cx, cy], [k1, k2, p1, p2, 0]),
    }[model]


@pytest.fixture
def model(rng):
    """A random model: one camera per supported model, 7 images (cameras shared, ids and
    names in different orders, names under a subfolder), 6 observations per image, 4 points
    seen by 2-3 images each."""
    rec = pycolmap.Reconstruction()
    cams = {}
    for cid, name in enumerate(MODELS, start=1):
        params, k, dist = _camera(rng, name)
        w, h = int(rng.integers(60, 90)), int(rng.integers(40, 60))
        rec.add_camera_with_trivial_rig(pycolmap.Camera(model=name, width=w, height=h, params=params, camera_id=cid))
        cams[cid] = dict(model=name, wh=(w, h), params=np.array(params), k=np.array(k), dist=np.array(dist))
    images = {}
    for iid, stem in zip(range(1, 8), rng.permutation(7)):
        rot, t = Rotation.random(random_state=rng).as_matrix(), rng.normal(size=3)  # pyright: ignore[reportCallIssue] -- scipy still takes random_state; its stubs name only rng
        xys = rng.uniform(0.0, 60.0, (6, 2))
        cid = 1 + (iid % len(MODELS))
        name = f"views/{stem:03d}.png"
        rec.add_image_with_trivial_frame(
            pycolmap.Image(name=name, keypoints=xys, camera_id=cid, image_id=iid),
            pycolmap.Rigid3d(pycolmap.Rotation3d(rot), t),
        )
        c2w = np.eye(4)
        c2w[:3, :3], c2w[:3, 3] = rot.T, -rot.T @ t
        images[iid] = dict(name=name, camera_id=cid, c2w=c2w, xys=xys, point3d_ids=np.full(6, -1))
    points = {}
    for j in range(4):
        seen = rng.choice(np.arange(1, 8), size=int(rng.integers(2, 4)), replace=False)
        track = pycolmap.Track()
        for iid in seen:
            track.add_element(int(iid), j)
        xyz, rgb = rng.normal(size=3), rng.integers(0, 256, 3)
        pid = rec.add_point3D(xyz, track, rgb.astype(np.uint8))
        rec.point3D(pid).error = float(rng.uniform(0.1, 2.0))
        for iid in seen:
            images[int(iid)]["point3d_ids"][j] = pid
        points[pid] = dict(
            xyz=xyz, rgb=rgb, error=rec.point3D(pid).error, image_ids=seen, point2d_idxs=np.full(len(seen), j)
        )
    return rec, cams, images, points


def _write(rec, folder, binary):
    os.makedirs(folder)
    (rec.write_binary if binary else rec.write_text)(folder)
    return folder


@pytest.mark.parametrize("binary", [True, False])
def test_reads_a_model_written_by_pycolmap(tmp_path, model, binary):
    rec, cams, images, points = model
    sparse = _write(rec, str(tmp_path / "sparse"), binary)
    assert os.path.exists(os.path.join(sparse, "cameras.bin" if binary else "cameras.txt"))
    got_cams, got_imgs, got_pts = read_colmap_model(sparse)
    assert sorted(got_cams) == sorted(cams) and sorted(got_imgs) == sorted(images) and sorted(got_pts) == sorted(points)
    for cid, want in cams.items():
        cam = got_cams[cid]
        assert (cam.model, (cam.width, cam.height)) == (want["model"], want["wh"])
        np.testing.assert_allclose(cam.params, want["params"], rtol=TOL)
        k, dist = cam.pinhole_and_distortion()
        np.testing.assert_allclose(k, want["k"], rtol=TOL)
        np.testing.assert_allclose(dist, want["dist"], rtol=TOL, atol=0)
    for iid, want in images.items():
        im = got_imgs[iid]
        assert (im.name, im.camera_id) == (want["name"], want["camera_id"])
        np.testing.assert_allclose(im.c2w, want["c2w"], atol=TOL)
        np.testing.assert_allclose(im.xys, want["xys"], rtol=TOL)
        np.testing.assert_array_equal(im.point3d_ids, want["point3d_ids"])
    for pid, want in points.items():
        p = got_pts[pid]
        np.testing.assert_allclose(p.xyz, want["xyz"], rtol=TOL)
        np.testing.assert_array_equal(p.rgb, want["rgb"])
        assert p.error == pytest.approx(want["error"], rel=TOL)
        np.testing.assert_array_equal(p.image_ids, want["image_ids"])
        np.testing.assert_array_equal(p.point2d_idxs, want["point2d_idxs"])


@pytest.mark.parametrize("binary", [True, False])
def test_scene_orders_by_name_with_each_images_camera(tmp_path, model, binary):
    """The scene lists the images sorted by name, each found under the image folder at its
    model name (subfolder included), with its own camera's intrinsics and distortion;
    ``points3D`` is not needed for it."""
    rec, cams, images, _ = model
    sparse = _write(rec, str(tmp_path / "sparse"), binary)
    for want in images.values():
        w, h = cams[want["camera_id"]]["wh"]
        write_image(str(tmp_path / "images" / want["name"]), np.full((h, w, 3), 0.5, np.float32), bits=8)
    os.remove(os.path.join(sparse, "points3D.bin" if binary else "points3D.txt"))
    scene = read_colmap_scene(sparse, str(tmp_path / "images"))
    order = sorted(images.values(), key=lambda im: im["name"])
    assert [os.path.relpath(f, tmp_path / "images") for f in scene.frame_names] == [im["name"] for im in order]
    np.testing.assert_allclose(scene.c2w, np.stack([im["c2w"] for im in order]), atol=TOL)
    np.testing.assert_allclose(scene.intrinsics, np.stack([cams[im["camera_id"]]["k"] for im in order]), rtol=TOL)
    np.testing.assert_allclose(scene.distortion, np.stack([cams[im["camera_id"]]["dist"] for im in order]), rtol=TOL)  # pyright: ignore[reportArgumentType, reportCallIssue] -- the written cameras have distortion
    np.testing.assert_array_equal(scene.hw, [cams[im["camera_id"]]["wh"][::-1] for im in order])
    with pytest.raises(MissingInputError, match="points3D"):
        read_colmap_model(sparse)


def _cut(path, keep):
    data = open(path, "rb").read()
    open(path, "wb").write(data[:keep] if keep >= 0 else data[:keep])


def test_damaged_binary_files_are_one_line_naming_the_file(tmp_path, model):
    """Cut short at the end (COLMAP reads such a file without complaint), emptied (COLMAP
    would loop on the garbage count), or with a count beyond the file's size."""
    rec = model[0]
    cases = [
        ("images.bin", lambda p: _cut(p, -5), r"images.bin: \d+ bytes, but the images it lists take \d+"),
        ("cameras.bin", lambda p: _cut(p, -3), r"cameras.bin: \d+ bytes, but the cameras it lists take \d+"),
        ("points3D.bin", lambda p: _cut(p, -1), r"points3D.bin: \d+ bytes, but the points3D it lists take"),
        ("points3D.bin", lambda p: _cut(p, 0), r"points3D.bin: file is truncated \(0 bytes; needs an 8-byte"),
        ("images.bin", lambda p: _cut(p, 50), r"images.bin: file is truncated \(50 bytes; needs at least \d+ for 7"),
    ]
    for k, (name, damage, message) in enumerate(cases):
        sparse = _write(rec, str(tmp_path / str(k)), binary=True)
        damage(os.path.join(sparse, name))
        with pytest.raises(ValueError, match=message) as caught:
            read_colmap_model(sparse)
        assert "\n" not in str(caught.value)


def _edit_line(path, first_field, field, value):
    """Replace field ``field`` of the data line starting with ``first_field``."""
    lines = open(path).read().split("\n")
    k = next(i for i, ln in enumerate(lines) if ln.split(" ")[0] == first_field and not ln.startswith("#"))
    el = lines[k].split(" ")
    el[field] = value
    lines[k] = " ".join(el)
    open(path, "w").write("\n".join(lines))


def test_bad_text_files_are_one_line_naming_the_file(tmp_path, model):
    """A model pycolmap reads but this reader does not support (FISHEYE, a missing param),
    and ones pycolmap rejects (an unknown model, a pose that is not a number, an image on a
    camera the model lacks): each names the file at fault."""
    rec = model[0]
    cases = [
        ("cameras.txt", "2", 1, "FISHEYE", r"cameras.txt: camera 2 has unsupported model 'FISHEYE'"),
        (
            "cameras.txt",
            "5",
            11,
            "",
            r"cameras.txt: not a valid COLMAP text cameras file \(.*VerifyParams.*\); "
            r"expected .* as many PARAMS as the model has",
        ),
        ("cameras.txt", "3", 1, "BOGUS", r"cameras.txt: not a valid COLMAP text cameras file \(Camera model"),
        ("images.txt", "4", 2, "abc", r"images.txt: not a valid COLMAP text images file"),
        ("images.txt", "4", 8, "99", r"images.txt: not a valid COLMAP text images file"),
    ]
    for k, (name, first, field, value, message) in enumerate(cases):
        sparse = _write(rec, str(tmp_path / str(k)), binary=False)
        path = os.path.join(sparse, name)
        if value:
            _edit_line(path, first, field, value)
        else:  # drop the last param
            lines = open(path).read().split("\n")
            lines = [" ".join(ln.split(" ")[:-1]) if ln.split(" ")[0] == first else ln for ln in lines]
            open(path, "w").write("\n".join(lines))
        with pytest.raises(ValueError, match=message) as caught:
            read_colmap_model(sparse)
        assert "\n" not in str(caught.value)
