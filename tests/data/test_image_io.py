"""Image I/O (OpenImageIO), resampling and lens distortion against direct formulas,
scikit-image and kornia."""

import os

import numpy as np
import pytest
import torch
from kornia.geometry.calibration import distort_points, undistort_image, undistort_points

from llrmpp_jax.data import distortion as D
from llrmpp_jax.data.image_io import image_size, read_depth, read_image, write_depth, write_image
from llrmpp_jax.data.resample import remap, resize_depth, resize_image


def test_png_exr_round_trips(tmp_path, rng):
    img = rng.random((7, 9, 3)).astype(np.float32)
    q16 = (np.rint(img * 65535) / 65535).astype(np.float32)
    write_image(str(tmp_path / "a.png"), q16, bits=16)
    np.testing.assert_array_equal(read_image(str(tmp_path / "a.png")), q16)
    write_image(str(tmp_path / "b.png"), img, bits=8)
    np.testing.assert_array_equal(read_image(str(tmp_path / "b.png")), (np.rint(img * 255) / 255).astype(np.float32))
    write_image(str(tmp_path / "c.exr"), img, bits=32)
    np.testing.assert_array_equal(read_image(str(tmp_path / "c.exr")), img)
    yy, xx = np.mgrid[0:32, 0:32] / 32.0
    smooth = np.stack([xx, yy, 0.5 * (xx + yy)], axis=-1).astype(np.float32)  # JPEG is lossy
    write_image(str(tmp_path / "d.jpg"), smooth, bits=8)
    assert np.abs(read_image(str(tmp_path / "d.jpg")) - smooth).max() < 0.03
    assert image_size(str(tmp_path / "a.png")) == (7, 9)


def test_grey_image_becomes_rgb(tmp_path, rng):
    import OpenImageIO as oiio

    grey = (rng.random((5, 6)) * 255).astype(np.uint8)
    out = oiio.ImageOutput.create(str(tmp_path / "g.png"))
    out.open(str(tmp_path / "g.png"), oiio.ImageSpec(6, 5, 1, oiio.UINT8))  # pyright: ignore[reportOptionalMemberAccess] -- create() is None only for an unknown format; PNG is known
    out.write_image(grey[:, :, None])  # pyright: ignore[reportOptionalMemberAccess] -- as above
    out.close()  # pyright: ignore[reportOptionalMemberAccess] -- as above
    img = read_image(str(tmp_path / "g.png"))
    assert img.shape == (5, 6, 3)
    for c in range(3):
        np.testing.assert_array_equal(img[..., c], grey.astype(np.float32) / 255)


def test_depth_files(tmp_path, rng):
    depth = rng.uniform(0.3, 9.0, size=(6, 8)).astype(np.float32)
    depth[0, 0] = 0.0
    write_depth(str(tmp_path / "d.png"), depth, scale=1e-3)
    expect = (np.rint(depth.astype(np.float64) * 1000) * 1e-3).astype(np.float32)
    np.testing.assert_array_equal(read_depth(str(tmp_path / "d.png"), 1e-3), expect)
    write_depth(str(tmp_path / "d.exr"), depth, scale=None)
    np.testing.assert_array_equal(read_depth(str(tmp_path / "d.exr")), depth)
    with pytest.raises(ValueError, match=r"d2.png.*exceeds the 16-bit range"):
        write_depth(str(tmp_path / "d2.png"), depth * 10, scale=1e-3)


def test_unreadable_files_name_the_file(tmp_path, rng):
    with pytest.raises(FileNotFoundError, match="nope.png"):
        read_image(str(tmp_path / "nope.png"))
    (tmp_path / "junk.png").write_bytes(b"this is not an image")
    with pytest.raises(ValueError, match="junk.png"):
        read_image(str(tmp_path / "junk.png"))
    write_image(str(tmp_path / "full.jpg"), rng.random((64, 64, 3)).astype(np.float32))
    data = (tmp_path / "full.jpg").read_bytes()
    (tmp_path / "cut.jpg").write_bytes(data[: len(data) // 2])
    with pytest.raises(ValueError, match=r"cut.jpg.*(corrupt or truncated)"):
        read_image(str(tmp_path / "cut.jpg"))
    write_image(str(tmp_path / "e.png"), rng.random((4, 4, 3)).astype(np.float32), bits=8)
    with pytest.raises(ValueError, match=r"e.png: 8-bit depth"):
        read_depth(str(tmp_path / "e.png"))


def test_resize_image_maps_pixel_centres(rng):
    """A linear ramp stays the same linear function of continuous coordinates after
    resizing, shrinking and enlarging (interior pixels, away from border clamping)."""
    h, w, nh, nw = 40, 60, 24, 90
    a, b, c = rng.normal(size=3)
    yy, xx = np.mgrid[0:h, 0:w] + 0.5
    ramp = (a * xx / w + b * yy / h + c).astype(np.float32)[..., None]
    out = resize_image(ramp, (nh, nw))
    y2, x2 = np.mgrid[0:nh, 0:nw] + 0.5
    expect = a * x2 / nw + b * y2 / nh + c
    np.testing.assert_allclose(out[3:-3, 3:-3, 0], expect[3:-3, 3:-3], atol=1e-5)


def test_resize_depth_and_remap(rng):
    d = rng.random((6, 9)).astype(np.float32)
    up = resize_depth(d, (12, 27))
    np.testing.assert_array_equal(up, np.repeat(np.repeat(d, 2, axis=0), 3, axis=1))
    np.testing.assert_array_equal(resize_depth(up, (6, 9)), d)
    img = rng.random((6, 9, 2)).astype(np.float32)
    xy = np.stack(np.meshgrid(np.arange(9) + 0.5, np.arange(6) + 0.5, indexing="xy"), axis=-1)
    np.testing.assert_allclose(remap(img, xy), img, atol=1e-6)
    np.testing.assert_array_equal(remap(d, xy + 0.49, nearest=True), d)
    # half a pixel right: bilinear = mean of horizontal neighbours
    np.testing.assert_allclose(remap(img, xy + np.array([0.5, 0.0]))[:, :-1], (img[:, :-1] + img[:, 1:]) / 2, atol=1e-6)


COEFFS = np.array([0.0578421, -0.0805099, -0.000980296, 0.00015575, 0.01])


def kornia_k(intr, shift):
    fx, fy, cx, cy = intr
    return torch.tensor([[[fx, 0, cx + shift], [0, fy, cy + shift], [0, 0, 1.0]]], dtype=torch.float64)


def test_distortion_points_match_kornia(rng):
    intr = np.array([110.0, 105.0, 52.0, 41.0])
    pts = rng.uniform([0, 0], [100, 80], size=(50, 2))
    ours = D.distort_pixels(pts, intr, COEFFS)
    dist = torch.tensor(COEFFS[[0, 1, 2, 3, 4]], dtype=torch.float64)[None]
    ref = distort_points(torch.tensor(pts)[None], kornia_k(intr, 0.0), dist)[0].numpy()
    np.testing.assert_allclose(ours, ref, atol=1e-9)
    back = D.undistort_pixels(ours, intr, COEFFS)
    np.testing.assert_allclose(back, pts, atol=1e-8)
    ref_back = undistort_points(torch.tensor(ours)[None], kornia_k(intr, 0.0), dist, num_iters=50)[0].numpy()
    np.testing.assert_allclose(back, ref_back, atol=1e-6)


def test_undistort_image_matches_kornia(rng):
    """kornia indexes pixel centres at integers, we at +0.5: its K is ours shifted by -0.5."""
    h, w = 48, 64
    intr = np.array([70.0, 68.0, 31.0, 25.0])
    yy, xx = np.mgrid[0:h, 0:w]
    img = np.stack([np.sin(xx / 5.0 + c) * np.cos(yy / 7.0) * 0.5 + 0.5 for c in range(3)], axis=-1).astype(np.float32)
    ours = D.undistort_image(img, intr, COEFFS)
    t = torch.tensor(img, dtype=torch.float64).permute(2, 0, 1)[None]
    ref = undistort_image(t, kornia_k(intr, -0.5), torch.tensor(COEFFS, dtype=torch.float64)[None])
    ref = ref[0].permute(1, 2, 0).numpy()
    # interior (kornia pads outside samples with zeros, we clamp to the border)
    np.testing.assert_allclose(ours[4:-4, 4:-4], ref[4:-4, 4:-4], atol=1e-5)
    np.testing.assert_array_equal(D.undistort_image(img, intr, np.zeros(5)), img)


def test_undistorted_image_follows_pinhole_projection(rng):
    """A blob drawn where the distorted lens images a point ends up, after undistortion, at
    the point's pinhole projection."""
    h, w = 60, 80
    intr = np.array([60.0, 60.0, 40.0, 30.0])
    target = np.array([58.0, 17.0])  # ideal pinhole position
    xd, yd = D.distort_pixels(target, intr, COEFFS)
    yy, xx = np.mgrid[0:h, 0:w] + 0.5
    img = np.exp(-((xx - xd) ** 2 + (yy - yd) ** 2) / 8.0)[..., None].astype(np.float32)
    und = D.undistort_image(img, intr, COEFFS)[..., 0]
    centroid = np.array([(und * xx).sum(), (und * yy).sum()]) / und.sum()
    np.testing.assert_allclose(centroid, target, atol=0.15)
    assert os.path.basename(os.path.dirname(os.path.abspath(__file__))) == "data"  # filed among the data tests
