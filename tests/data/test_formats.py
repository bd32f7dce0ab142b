"""Every on-disk format: write a procedural scene, read it back, get the same images,
depth, intrinsics and cameras; and every kind of bad input fails with a message that
names the file and field."""

import json
import os
import warnings

import numpy as np
import pytest

from llrmpp_jax.data.formats import (
    FORMATS,
    READERS,
    read_colmap_model,
    read_colmap_scene,
    read_long_lrm_index,
    read_long_lrm_scene,
    read_nerfstudio_scene,
    read_re10k_scene,
    read_scannet_scene,
    write_colmap_scene,
    write_long_lrm_index,
    write_long_lrm_scene,
    write_nerfstudio_scene,
    write_re10k_scene,
    write_scannet_scene,
)
from llrmpp_jax.data.image_io import write_image
from llrmpp_jax.data.scene import Scene, in_memory_scene
from llrmpp_jax.data.synthetic import ProceduralConfig, procedural_scene
from llrmpp_jax.geometry import opencv_to_opengl

H, W, N = 20, 28, 4


@pytest.fixture(scope="module")
def source():
    """A small procedural scene held in memory: images on the 16-bit grid (so 16-bit PNG
    is lossless for them), depth on the millimetre grid (so ScanNet's format is too)."""
    s = procedural_scene(7, ProceduralConfig(height=H, width=W, num_frames=N))
    images = np.stack([np.rint(s.image(i) * 65535) / 65535 for i in range(N)]).astype(np.float32)
    depth = np.stack([np.rint(s.depth(i).astype(np.float64) * 1000) / 1000 for i in range(N)]).astype(np.float32)
    return in_memory_scene("roundtrip", images, s.c2w, s.intrinsics, depth)


def assert_same(a: Scene, b: Scene, depth=True):
    assert len(a) == len(b)
    np.testing.assert_allclose(b.c2w, a.c2w, rtol=0, atol=1e-6)
    np.testing.assert_allclose(b.intrinsics, a.intrinsics, rtol=1e-12, atol=1e-6)
    np.testing.assert_array_equal(b.hw, a.hw)
    for i in range(len(a)):
        np.testing.assert_array_equal(b.image(i), a.image(i))
        if depth:
            np.testing.assert_allclose(b.depth(i), a.depth(i), rtol=0, atol=1e-6)


def test_format_names_are_the_readers_and_auto():
    """``Format`` (the configs' and ``--format``'s names) lists exactly the readers."""
    assert set(FORMATS) == {"auto", *READERS} and len(FORMATS) == len(READERS) + 1


def test_long_lrm_round_trip(tmp_path, source):
    path = write_long_lrm_scene(source, str(tmp_path / "scene"))
    write_long_lrm_index(str(tmp_path / "data.txt"), [path])
    assert read_long_lrm_index(str(tmp_path / "data.txt")) == [path]
    back = read_long_lrm_scene(path)
    assert back.name == "roundtrip"
    assert_same(source, back)
    # png depth in millimetres instead of EXR metres
    path = write_long_lrm_scene(source, str(tmp_path / "scene_mm"), depth_ext=".png")
    assert_same(source, read_long_lrm_scene(path))


def test_long_lrm_reads_the_upstream_layout(tmp_path, source):
    """A JSON exactly as Long-LRM's processing script writes it (no depth keys, w2c)."""
    write_image(str(tmp_path / "images" / "a.png"), source.image(0), bits=16)
    fx, fy, cx, cy = source.intrinsics[0]
    w2c = np.linalg.inv(source.c2w[0])
    frames = [
        {"file_path": "images/a.png", "w2c": w2c.tolist(), "h": H, "w": W, "fx": fx, "fy": fy, "cx": cx, "cy": cy}
    ]
    with open(tmp_path / "opencv_cameras.json", "w") as f:
        json.dump({"scene_name": "up", "frames": frames, "fold_8_kmeans_32_input": [0]}, f)
    s = read_long_lrm_scene(str(tmp_path / "opencv_cameras.json"))
    assert not s.has_depth
    np.testing.assert_allclose(s.c2w[0], source.c2w[0], atol=1e-12)


def test_nerfstudio_round_trip(tmp_path, source):
    path = write_nerfstudio_scene(source, str(tmp_path))
    data = json.load(open(path))
    np.testing.assert_allclose(data["frames"][1]["transform_matrix"], opencv_to_opengl(source.c2w[1]), atol=1e-12)
    assert_same(source, read_nerfstudio_scene(str(tmp_path)))


def test_nerfstudio_shared_intrinsics_downscaled_folder_and_dl3dv_remap(tmp_path, source):
    """instant-ngp style: top-level intrinsics for full-size images, frames in a 2x smaller
    folder; Long-LRM's DL3DV world remap, transcribed from prosess_dl3dv.py."""
    fx, fy, cx, cy = source.intrinsics[0]
    frames = []
    for i in range(N):
        small = source.image(i)[::2, ::2]  # content is irrelevant here, only the size
        write_image(str(tmp_path / "images_2" / f"{i}.png"), small, bits=8)
        frames.append({"file_path": f"./images/{i}.png", "transform_matrix": opencv_to_opengl(source.c2w[i]).tolist()})
    with open(tmp_path / "transforms.json", "w") as f:
        json.dump(
            {"fl_x": fx * 2, "fl_y": fy * 2, "cx": cx * 2, "cy": cy * 2, "w": W * 2, "h": H * 2, "frames": frames}, f
        )
    s = read_nerfstudio_scene(str(tmp_path), image_dir="images_2", dl3dv_world_remap=True)
    # declared for 2x the source size, files at half the source size: a quarter of declared
    np.testing.assert_allclose(s.intrinsics, source.intrinsics / 2, atol=1e-12)
    np.testing.assert_array_equal(s.hw, np.tile([[H // 2, W // 2]], (N, 1)))
    for i in range(N):
        c2w = opencv_to_opengl(source.c2w[i]).copy()  # as stored in the json
        c2w[0:3, 1:3] *= -1
        c2w = c2w[[1, 0, 2, 3], :]
        c2w[2, :] *= -1
        np.testing.assert_allclose(s.c2w[i], c2w, atol=1e-12)


@pytest.mark.parametrize("binary", [True, False])
def test_colmap_round_trip(tmp_path, source, binary):
    sparse = write_colmap_scene(source, str(tmp_path), binary=binary)
    assert os.path.exists(os.path.join(sparse, "cameras.bin" if binary else "cameras.txt"))
    back = read_colmap_scene(sparse, str(tmp_path / "images"))
    assert_same(source, back, depth=False)
    cams, imgs, pts = read_colmap_model(sparse)
    assert len(cams) == N and len(imgs) == N and len(pts) == 0


def test_scannet_round_trip(tmp_path, source):
    write_scannet_scene(source, str(tmp_path))
    assert_same(source, read_scannet_scene(str(tmp_path), resolution="depth"))
    assert_same(source, read_scannet_scene(str(tmp_path), resolution="color"))


def test_scannet_registers_depth_into_the_colour_camera(tmp_path, rng):
    """Colour at 2x the depth size with slightly different intrinsics: the depth returned
    at pixel p is the depth-camera sample at K_d K_c'^-1 p (nearest), p in the output grid."""
    hc, wc, hd, wd = 24, 32, 12, 16
    kc = np.array([30.0, 30.0, 16.0, 12.0])
    kd = np.array([15.5, 15.2, 8.2, 5.9])
    for d in ("color", "depth", "pose", "intrinsic"):
        os.makedirs(tmp_path / d)
    depth = rng.uniform(0.5, 5.0, size=(hd, wd)).astype(np.float32)  # write_depth stores float32 depths
    from llrmpp_jax.data.image_io import write_depth

    for i in range(2):
        write_image(str(tmp_path / "color" / f"{i}.png"), rng.random((hc, wc, 3)).astype(np.float32), bits=8)
        write_depth(str(tmp_path / "depth" / f"{i}.png"), depth, scale=1e-3)
        np.savetxt(tmp_path / "pose" / f"{i}.txt", np.eye(4))
    for name, k in (("intrinsic_color.txt", kc), ("intrinsic_depth.txt", kd)):
        np.savetxt(tmp_path / "intrinsic" / name, [[k[0], 0, k[2], 0], [0, k[1], k[3], 0], [0, 0, 1, 0], [0, 0, 0, 1]])
    s = read_scannet_scene(str(tmp_path), resolution="depth")
    k_out = kc / 2
    np.testing.assert_allclose(s.intrinsics[0], k_out)
    got = s.depth(1)
    stored = np.rint(depth.astype(np.float64) / 1e-3) * 1e-3  # write_depth's rounding, at its precision
    for i in range(hd):
        for j in range(wd):
            xd = (j + 0.5 - k_out[2]) / k_out[0] * kd[0] + kd[2]
            yd = (i + 0.5 - k_out[3]) / k_out[1] * kd[1] + kd[3]
            expect = stored[min(max(int(np.floor(yd)), 0), hd - 1), min(max(int(np.floor(xd)), 0), wd - 1)]
            assert abs(got[i, j] - expect) < 1e-6


@pytest.mark.parametrize("normalized", [False, True])
def test_re10k_round_trip(tmp_path, source, normalized):
    path = write_re10k_scene(source, str(tmp_path), normalized=normalized)
    assert bool((np.asarray(json.load(open(path))["frames"][0]["fxfycxcy"])[2:] < 1).all()) == normalized
    assert_same(source, read_re10k_scene(path), depth=False)


# ---------------------------------------------------------------- bad input


def test_missing_images_are_skipped_with_one_counting_warning(tmp_path, source):
    path = write_long_lrm_scene(source, str(tmp_path))
    os.remove(tmp_path / "images" / "00001.png")
    os.remove(tmp_path / "images" / "00003.png")
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        s = read_long_lrm_scene(path)
    msgs = [str(w.message) for w in caught]
    assert len(msgs) == 1 and "skipped 2 of 4 frames" in msgs[0] and "00001.png" in msgs[0]
    assert len(s) == 2
    np.testing.assert_allclose(s.c2w, source.c2w[[0, 2]], atol=1e-12)
    with pytest.raises(FileNotFoundError, match="00001.png"):
        read_long_lrm_scene(path, missing="error")
    for name in ("00000.png", "00002.png"):
        os.remove(tmp_path / "images" / name)
    with pytest.raises(ValueError, match="empty scene"), warnings.catch_warnings():
        warnings.simplefilter("ignore")
        read_long_lrm_scene(path)


def edit_frame(path, index, **changes):
    data = json.load(open(path))
    data["frames"][index].update(changes)
    json.dump(data, open(path, "w"))


def test_bad_poses_and_intrinsics_name_file_frame_and_field(tmp_path, source):
    path = write_long_lrm_scene(source, str(tmp_path))
    good = json.load(open(path))
    w2c = np.array(good["frames"][2]["w2c"])
    edit_frame(path, 2, w2c=np.where(np.eye(4) == 1, np.inf, w2c).tolist())
    with pytest.raises(ValueError, match=r"opencv_cameras.json, frame 2.*w2c.*non-finite"):
        read_long_lrm_scene(path)
    json.dump(good, open(path, "w"))
    sheared = w2c.copy()
    sheared[0, 1] += 0.3
    edit_frame(path, 2, w2c=sheared.tolist())
    with pytest.raises(ValueError, match=r"opencv_cameras.json, frame 2 \(.*00002.png\).*not a rotation"):
        read_long_lrm_scene(path)
    json.dump(good, open(path, "w"))
    edit_frame(path, 1, fx=0.0)
    with pytest.raises(ValueError, match=r"frame 1 \(.*00001.png\).*focal lengths must be > 0"):
        read_long_lrm_scene(path)
    json.dump(good, open(path, "w"))
    del good["frames"][3]["cy"]
    json.dump(good, open(path, "w"))
    with pytest.raises(ValueError, match=r"frame 3: bad or missing field 'cy'"):
        read_long_lrm_scene(path)


def test_bad_files_fail_at_load_naming_the_file(tmp_path, source):
    path = write_long_lrm_scene(source, str(tmp_path))
    s = read_long_lrm_scene(path)
    data = (tmp_path / "images" / "00001.png").read_bytes()
    (tmp_path / "images" / "00001.png").write_bytes(data[: len(data) // 3])
    with pytest.raises(ValueError, match="00001.png"):
        s.image(1)
    write_image(str(tmp_path / "images" / "00002.png"), np.zeros((H + 2, W, 3), np.float32))
    with pytest.raises(
        ValueError, match=r"frame 2 \(.*00002.png\): image has shape \(22, 28, 3\), expected \[20, 28, 3\]"
    ):
        s.image(2)
    from llrmpp_jax.data.image_io import write_depth

    write_depth(str(tmp_path / "depth" / "00003.exr"), np.ones((H, W + 1), np.float32), scale=None)
    with pytest.raises(ValueError, match=r"00003.png\): depth map has shape \(20, 29\), expected \[20, 28\]"):
        s.depth(3)
    os.remove(tmp_path / "images" / "00000.png")
    with pytest.raises(FileNotFoundError, match="00000.png"):
        s.image(0)


def test_scannet_skips_invalid_poses(tmp_path, source):
    write_scannet_scene(source, str(tmp_path))
    np.savetxt(tmp_path / "pose" / "2.txt", np.full((4, 4), -np.inf))
    with pytest.warns(UserWarning, match="skipped 1 frames with invalid"):
        s = read_scannet_scene(str(tmp_path))
    assert len(s) == N - 1
    np.testing.assert_allclose(s.c2w, source.c2w[[0, 1, 3]], atol=1e-12)


def test_colmap_truncated_and_unsupported(tmp_path, source):
    sparse = write_colmap_scene(source, str(tmp_path), binary=True)
    data = open(os.path.join(sparse, "images.bin"), "rb").read()
    open(os.path.join(sparse, "images.bin"), "wb").write(data[:50])
    with pytest.raises(ValueError, match=r"images.bin: file is truncated"):
        read_colmap_model(sparse)
    sparse = write_colmap_scene(source, str(tmp_path / "t"), binary=False)
    txt = open(os.path.join(sparse, "cameras.txt")).read().replace("PINHOLE", "FISHEYE", 1)
    open(os.path.join(sparse, "cameras.txt"), "w").write(txt)
    with pytest.raises(ValueError, match=r"cameras.txt: camera 1 has unsupported model 'FISHEYE'"):
        read_colmap_model(sparse)


@pytest.mark.parametrize(
    "model,params",
    [
        ("SIMPLE_PINHOLE", [100.0, 30.0, 20.0]),
        ("PINHOLE", [100.0, 90.0, 30.0, 20.0]),
        ("SIMPLE_RADIAL", [100.0, 30.0, 20.0, 0.08]),
        ("RADIAL", [100.0, 30.0, 20.0, 0.08, -0.03]),
        ("OPENCV", [100.0, 90.0, 30.0, 20.0, 0.08, -0.03, 0.002, -0.001]),
    ],
)
def test_colmap_camera_models_match_colmap_equations(rng, model, params):
    """Projection of normalised points with COLMAP's own model equations (written out
    here) equals pinhole intrinsics + OpenCV distortion from ``pinhole_and_distortion``."""
    from llrmpp_jax.data.distortion import distort_pixels
    from llrmpp_jax.data.formats.colmap import ColmapCamera

    p = np.array(params)
    xy = rng.uniform(-0.3, 0.3, size=(20, 2))
    u, v = xy[:, 0], xy[:, 1]
    r2 = u * u + v * v
    if model == "SIMPLE_PINHOLE":
        expect = np.stack([p[0] * u + p[1], p[0] * v + p[2]], 1)
    elif model == "PINHOLE":
        expect = np.stack([p[0] * u + p[2], p[1] * v + p[3]], 1)
    elif model == "SIMPLE_RADIAL":
        expect = np.stack([p[0] * u * (1 + p[3] * r2) + p[1], p[0] * v * (1 + p[3] * r2) + p[2]], 1)
    elif model == "RADIAL":
        rad = 1 + p[3] * r2 + p[4] * r2 * r2
        expect = np.stack([p[0] * u * rad + p[1], p[0] * v * rad + p[2]], 1)
    else:
        k1, k2, p1, p2 = p[4:]
        rad = 1 + k1 * r2 + k2 * r2 * r2
        du = 2 * p1 * u * v + p2 * (r2 + 2 * u * u)
        dv = 2 * p2 * u * v + p1 * (r2 + 2 * v * v)
        expect = np.stack([p[0] * (u * rad + du) + p[2], p[1] * (v * rad + dv) + p[3]], 1)
    k, dist = ColmapCamera(1, model, 64, 48, p).pinhole_and_distortion()
    pinhole = xy * k[:2] + k[2:]
    np.testing.assert_allclose(distort_pixels(pinhole, k, dist), expect, atol=1e-10)


def test_subset_reindexes_loaders(source):
    sub = source.subset([3, 1])
    np.testing.assert_array_equal(sub.image(0), source.image(3))
    np.testing.assert_array_equal(sub.depth(1), source.depth(1))
    np.testing.assert_array_equal(sub.c2w, source.c2w[[3, 1]])
    with pytest.raises(ValueError, match=r"subset indices"):
        source.subset([4])
