"""Camera geometry against plain per-pixel loops, the Long-LRM golden ray features, an
independent resampler (scikit-image) and a literal transcription of Long-LRM's pose
normalisation."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
import skimage.transform

from llrmpp_jax import geometry as G
from tests.helpers.environment import GOLDEN, shared_path
from tests.helpers.typechecks import unchecked


def random_c2w(rng, shape):
    """Random rigid OpenCV c2w ``[*shape, 4, 4]`` (proper rotations via QR)."""
    q, r = np.linalg.qr(rng.normal(size=shape + (3, 3)))
    q = q * np.sign(np.diagonal(r, axis1=-2, axis2=-1))[..., None, :]
    q[np.linalg.det(q) < 0, :, 0] *= -1
    out = np.zeros(shape + (4, 4))
    out[..., :3, :3] = q
    out[..., :3, 3] = rng.normal(size=shape + (3,)) * 2
    out[..., 3, 3] = 1
    return out


def random_intrinsics(rng, shape, h, w):
    f = rng.uniform(0.7, 1.5, size=shape + (2,)) * w
    c = np.stack([rng.uniform(0.3, 0.7, size=shape) * w, rng.uniform(0.3, 0.7, size=shape) * h], axis=-1)
    return np.concatenate([f, c], axis=-1)


def loop_rays(c2w, k, h, w):
    o = np.zeros((h, w, 3))
    d = np.zeros((h, w, 3))
    for i in range(h):
        for j in range(w):
            cam = np.array([(j + 0.5 - k[2]) / k[0], (i + 0.5 - k[3]) / k[1], 1.0])
            ray = c2w[:3, :3] @ cam
            d[i, j] = ray / np.sqrt(ray @ ray)
            o[i, j] = c2w[:3, 3]
    return o, d


def test_pixel_rays_match_loop(rng):
    h, w = 5, 7
    c2w = random_c2w(rng, (2, 3))
    k = random_intrinsics(rng, (2, 3), h, w)
    o, d = G.pixel_rays(c2w, k, h, w)
    assert o.shape == d.shape == (2, 3, h, w, 3) and isinstance(o, np.ndarray)
    for a in range(2):
        for b in range(3):
            lo, ld = loop_rays(c2w[a, b], k[a, b], h, w)
            np.testing.assert_allclose(o[a, b], lo, atol=1e-12)
            np.testing.assert_allclose(d[a, b], ld, atol=1e-12)


def test_rays_through_arbitrary_pixels_match_loop(rng):
    c2w = random_c2w(rng, (2,))
    k = random_intrinsics(rng, (2,), 10, 10)
    uv = rng.uniform(0, 10, size=(2, 5, 2))
    o, d = G.rays_through_pixels(c2w[:, None], k[:, None], uv)
    for v in range(2):
        for p in range(5):
            cam = np.array([(uv[v, p, 0] - k[v, 2]) / k[v, 0], (uv[v, p, 1] - k[v, 3]) / k[v, 1], 1.0])
            ray = c2w[v, :3, :3] @ cam
            np.testing.assert_allclose(d[v, p], ray / np.linalg.norm(ray), atol=1e-12)
            np.testing.assert_allclose(o[v, p], c2w[v, :3, 3], atol=1e-12)


def test_pixel_rays_and_plucker_jit_float32(rng):
    h, w = 6, 4
    c2w = random_c2w(rng, (3,))
    k = random_intrinsics(rng, (3,), h, w)
    fn = jax.jit(lambda c, kk: G.plucker(*G.pixel_rays(c, kk, h, w)), static_argnums=())
    out = fn(jnp.asarray(c2w, jnp.float32), jnp.asarray(k, jnp.float32))
    assert out.dtype == jnp.float32 and out.shape == (3, h, w, 6)
    ref = G.plucker(*G.pixel_rays(c2w, k, h, w))
    np.testing.assert_allclose(np.asarray(out), ref, atol=2e-5)


def test_rays_match_long_lrm_golden():
    """Channels 3:9 of Long-LRM's per-pixel features are [o x d, d] from the official code.
    Long-LRM normalises before rotating, we after; with the fixture's float32-rounded
    rotations (|R^T R - I| ~ 4e-8) the two differ by that much, hence atol 1e-7."""
    inputs = np.load(shared_path("golden", "long_lrm_tiny", "inputs.npz"))
    golden = np.load(f"{GOLDEN}/outputs.npz")["pixel_features"]
    c2w = inputs["c2ws"].astype(np.float64)
    k = inputs["intrinsics"].astype(np.float64)
    h, w = golden.shape[2:4]
    feats = G.plucker(*G.pixel_rays(c2w, k, h, w))
    np.testing.assert_allclose(feats, golden[..., 3:], rtol=0, atol=1e-7)


def test_plucker_matches_cross(rng):
    o = rng.normal(size=(4, 5, 3))
    d = rng.normal(size=(4, 5, 3))
    p = G.plucker(o, d)
    m = np.stack(
        [
            o[..., 1] * d[..., 2] - o[..., 2] * d[..., 1],
            o[..., 2] * d[..., 0] - o[..., 0] * d[..., 2],
            o[..., 0] * d[..., 1] - o[..., 1] * d[..., 0],
        ],
        axis=-1,
    )
    np.testing.assert_allclose(p, np.concatenate([m, d], axis=-1), atol=1e-14)


def test_project_and_unproject_match_loop(rng):
    h, w = 4, 6
    c2w = random_c2w(rng, (2,))
    k = random_intrinsics(rng, (2,), h, w)
    depth = rng.uniform(0.5, 4.0, size=(2, h, w))
    pts = G.unproject_depth(depth, c2w, k)
    for v in range(2):
        for i in range(h):
            for j in range(w):
                cam = np.array([(j + 0.5 - k[v, 2]) / k[v, 0], (i + 0.5 - k[v, 3]) / k[v, 1], 1.0]) * depth[v, i, j]
                np.testing.assert_allclose(pts[v, i, j], c2w[v, :3, :3] @ cam + c2w[v, :3, 3], atol=1e-12)
    px, z = G.project_points(pts.reshape(2, -1, 3), c2w, k)
    grid = np.stack(np.meshgrid(np.arange(w) + 0.5, np.arange(h) + 0.5, indexing="xy"), axis=-1).reshape(-1, 2)
    np.testing.assert_allclose(px, np.broadcast_to(grid, (2, h * w, 2)), atol=1e-10)
    np.testing.assert_allclose(z, depth.reshape(2, -1), atol=1e-12)


def blob_image(h, w, x, y, sigma):
    yy, xx = np.mgrid[0:h, 0:w] + 0.5
    return np.exp(-((xx - x) ** 2 + (yy - y) ** 2) / (2 * sigma**2))


def centroid(img):
    yy, xx = np.mgrid[0 : img.shape[0], 0 : img.shape[1]] + 0.5
    return np.array([(img * xx).sum() / img.sum(), (img * yy).sum() / img.sum()])


def test_resize_and_crop_intrinsics_follow_the_image(rng):
    """A point projected through the updated intrinsics lands where an independent
    resampler (scikit-image) moved the image content that marks it."""
    h, w = 60, 80
    c2w = random_c2w(rng, ())
    k = random_intrinsics(rng, (), h, w)
    # a point seen well inside the image, so the blob marking it is not cut by the border
    x, y = rng.uniform(0.3, 0.7) * w, rng.uniform(0.3, 0.7) * h
    cam = np.array([(x - k[2]) / k[0], (y - k[3]) / k[1], 1.0]) * rng.uniform(2, 5)
    point = (c2w[:3, :3] @ cam + c2w[:3, 3])[None]
    img = blob_image(h, w, x, y, sigma=4.0)
    for new_hw in [(45, 100), (120, 72)]:
        resized = skimage.transform.resize(img, new_hw, order=1, anti_aliasing=False, mode="edge")
        k2 = G.resize_intrinsics(k, (h, w), new_hw)
        px, _ = G.project_points(point, c2w, k2)
        np.testing.assert_allclose(centroid(resized), px[0], atol=0.05)
    top, left = 7, 11
    k3 = G.crop_intrinsics(k, top, left)
    px, _ = G.project_points(point, c2w, k3)
    np.testing.assert_allclose(centroid(img[top:, left:]), px[0], atol=0.02)
    # per-view crop offsets on a batch
    kb = np.stack([k, k])
    out = G.crop_intrinsics(kb, np.array([1.0, 2.0]), np.array([3.0, 4.0]))
    np.testing.assert_allclose(out[:, 2:], kb[:, 2:] - np.array([[3.0, 1.0], [4.0, 2.0]]))


def long_lrm_normalize(in_c2w, tg_c2w, scene_scale=1.0):
    """Literal transcription of Long-LRM data/dataset.py (torch ops -> numpy)."""
    position_avg = in_c2w[:, :3, 3].mean(0)
    forward_avg = in_c2w[:, :3, 2].mean(0)
    down_avg = in_c2w[:, :3, 1].mean(0)
    forward_avg = forward_avg / np.linalg.norm(forward_avg)
    down_avg = down_avg - down_avg.dot(forward_avg) * forward_avg
    down_avg = down_avg / np.linalg.norm(down_avg)
    right_avg = np.cross(down_avg, forward_avg)
    pos_avg = np.stack([right_avg, down_avg, forward_avg, position_avg], axis=1)
    pos_avg = np.concatenate([pos_avg, [[0, 0, 0, 1]]], axis=0)
    pos_avg_inv = np.linalg.inv(pos_avg)
    in_c2w = pos_avg_inv[None] @ in_c2w
    tg_c2w = pos_avg_inv[None] @ tg_c2w
    scale = 1.0 / (scene_scale * np.abs(in_c2w[:, :3, 3]).max())
    in_c2w[:, :3, 3] *= scale
    tg_c2w[:, :3, 3] *= scale
    return in_c2w, tg_c2w, scale


@pytest.mark.parametrize("scene_scale", [1.0, 1.35])
def test_normalize_scene_matches_long_lrm_and_inverts(rng, scene_scale):
    inp = random_c2w(rng, (6,))
    inp[:, :3, 3] += np.array([10.0, -3.0, 2.0])
    tgt = random_c2w(rng, (4,))
    n_in, n_tg, transform, scale = G.normalize_scene(inp, tgt, scene_scale=scene_scale)
    r_in, r_tg, r_scale = long_lrm_normalize(inp.copy(), tgt.copy(), scene_scale)
    np.testing.assert_allclose(n_in, r_in, atol=1e-12)
    np.testing.assert_allclose(n_tg, r_tg, atol=1e-12)
    np.testing.assert_allclose(scale, r_scale, rtol=1e-12)
    # properties: mean pose -> identity axes at the origin, inputs inside [-1, 1]^3
    np.testing.assert_allclose(n_in[:, :3, 3].mean(0), 0, atol=1e-12)
    fwd = n_in[:, :3, 2].mean(0)
    np.testing.assert_allclose(fwd / np.linalg.norm(fwd), [0, 0, 1], atol=1e-12)
    down = n_in[:, :3, 1].mean(0)
    assert abs(down[0]) < 1e-12 and down[1] > 0
    np.testing.assert_allclose(np.abs(n_in[:, :3, 3]).max(), 1.0 / scene_scale, rtol=1e-12)
    # the transform maps world points to normalised points consistently with the cameras
    x = rng.normal(size=(5, 3))
    xn = x @ transform[:3, :3].T + transform[:3, 3]
    px, z = G.project_points(x[None].repeat(4, 0), tgt, np.tile([[50.0, 50, 20, 20]], (4, 1)))
    pxn, zn = G.project_points(xn[None].repeat(4, 0), n_tg, np.tile([[50.0, 50, 20, 20]], (4, 1)))
    np.testing.assert_allclose(pxn, px, atol=1e-9)
    np.testing.assert_allclose(zn, z * scale, rtol=1e-10)
    # round trip
    np.testing.assert_allclose(G.denormalize_poses(n_tg, transform), tgt, atol=1e-12)
    np.testing.assert_allclose(G.denormalize_poses(n_in, transform), inp, atol=1e-12)


def test_normalize_scene_without_rescale_is_the_rigid_part(rng):
    """``rescale=False``: scale 1, and the poses are Long-LRM's (float64 reference above)
    with the translations divided by its scale: the same centring and rotation, world units."""
    inp = random_c2w(rng, (6,))
    inp[:, :3, 3] += np.array([10.0, -3.0, 2.0])
    tgt = random_c2w(rng, (4,))
    n_in, n_tg, transform, scale = G.normalize_scene(inp, tgt, scene_scale=1.35, rescale=False)
    r_in, r_tg, r_scale = long_lrm_normalize(inp.copy(), tgt.copy(), 1.35)
    assert float(scale) == 1.0 and abs(float(r_scale) - 1.0) > 0.01
    for got, ref in ((n_in, r_in), (n_tg, r_tg)):
        np.testing.assert_allclose(got[:, :3, :3], ref[:, :3, :3], atol=1e-12)
        np.testing.assert_allclose(got[:, :3, 3], ref[:, :3, 3] / r_scale, atol=1e-12)
    dist = lambda c: np.linalg.norm(c[:, None, :3, 3] - c[None, :, :3, 3], axis=-1)  # noqa: E731
    np.testing.assert_allclose(dist(np.concatenate([n_in, n_tg])), dist(np.concatenate([inp, tgt])), atol=1e-12)
    np.testing.assert_allclose(G.denormalize_poses(n_tg, transform), tgt, atol=1e-12)


def test_normalize_scene_jit_and_single_view(rng):
    inp = random_c2w(rng, (5,))
    out = jax.jit(G.normalize_scene)(jnp.asarray(inp, jnp.float32))
    ref = G.normalize_scene(inp)
    np.testing.assert_allclose(np.asarray(out[0]), ref[0], atol=2e-5)
    assert out[0].dtype == jnp.float32
    one, tf, s = G.normalize_scene(inp[:1])  # a single view cannot be scaled: scale 1
    assert s == 1.0 and np.all(np.isfinite(one))
    np.testing.assert_allclose(one[0], np.eye(4), atol=1e-12)


def test_opengl_opencv_involution(rng):
    c2w = random_c2w(rng, (3,))
    gl = G.opencv_to_opengl(c2w)
    np.testing.assert_allclose(gl[:, :, 0], c2w[:, :, 0])
    np.testing.assert_allclose(gl[:, :, 1:3], -c2w[:, :, 1:3])
    np.testing.assert_allclose(gl[:, :, 3], c2w[:, :, 3])
    np.testing.assert_allclose(G.opengl_to_opencv(gl), c2w)
    # a point in front of an OpenCV camera (z > 0) is behind the OpenGL axes (z < 0)
    x = c2w[0, :3, 3] + c2w[0, :3, 2]
    assert (np.linalg.inv(gl[0]) @ np.append(x, 1))[2] < 0


def test_validate_cameras_errors(rng):
    c2w = random_c2w(rng, (3,))
    k = random_intrinsics(rng, (3,), 10, 10)
    G.validate_cameras(c2w, k)
    names = ["a.png", "b.png", "c.png"]
    bad = c2w.copy()
    bad[1, 0, 3] = np.nan
    with pytest.raises(ValueError, match=r"scan.*frame 1 \(b.png\).*c2w.*non-finite"):
        G.validate_cameras(bad, k, name="scan", frame_names=names)
    bad = c2w.copy()
    bad[2, :3, :3] *= 1.1
    with pytest.raises(ValueError, match=r"frame 2.*not a rotation"):
        G.validate_cameras(bad, k)
    bad = c2w.copy()
    bad[0, :3, 0] *= -1  # reflection
    with pytest.raises(ValueError, match=r"frame 0.*det"):
        G.validate_cameras(bad, k)
    badk = k.copy()
    badk[1, 1] = 0.0
    with pytest.raises(ValueError, match=r"frame 1.*focal"):
        G.validate_cameras(c2w, badk)
    with pytest.raises(ValueError, match=r"\[N, 4, 4\]"):
        G.validate_cameras(c2w[:, :3], k)
    with pytest.raises(ValueError, match=r"intrinsics must have shape \[3, 4\]"):
        G.validate_cameras(c2w, k[:, :3])


def test_shape_errors(rng):
    with pytest.raises(ValueError, match=r"c2w: expected shape \[\.\.\., 4, 4\], got \(3, 3\)"), unchecked():
        G.pixel_rays(np.eye(3), np.ones(4), 2, 2)
    with pytest.raises(ValueError, match=r"intrinsics: expected shape \[2, 4\]"):
        G.pixel_rays(random_c2w(rng, (2,)), np.ones((3, 4)), 2, 2)
    with pytest.raises(ValueError, match="directions"):
        G.plucker(np.ones((2, 3)), np.ones((3, 3)))
