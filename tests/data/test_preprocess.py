"""Preprocessing: Long-LRM's size rule, and exact intrinsics through resize, square crop
and zoom crop (checked on images that are known functions of pixel position), plus the
scene normalisation of a sample."""

import numpy as np
import pytest

from llrmpp_jax.data.preprocess import (
    ViewGeometry,
    crop_box,
    load_views,
    make_sample,
    output_size,
    resized_size,
    zoom_offset,
)
from llrmpp_jax.data.scene import in_memory_scene
from llrmpp_jax.data.synthetic import ProceduralConfig, procedural_scene
from llrmpp_jax.geometry import normalize_scene, project_points, unproject_depth


def long_lrm_size(h, w, resize_h, resize_w, patch):
    """Transcribed from Long-LRM Dataset.process_frames."""
    if resize_h == -1 and resize_w == -1:
        resize_h, resize_w = h, w
    elif resize_h == -1:
        resize_h = int(resize_w / w * h)
    elif resize_w == -1:
        resize_w = int(resize_h / h * w)
    return int(round(resize_h / patch)) * patch, int(round(resize_w / patch)) * patch


@pytest.mark.parametrize(
    "hw,rh,rw,m",
    [
        ((540, 960), 540, None, 16),
        ((1920, 1080), 256, None, 8),
        ((968, 1296), None, 448, 8),
        ((1080, 1920), None, None, 16),
        ((480, 640), 336, 448, 8),
    ],
)
def test_resized_size_matches_long_lrm(hw, rh, rw, m):
    got = resized_size(hw, ViewGeometry(resize_h=rh, resize_w=rw, multiple=m))
    assert got == long_lrm_size(*hw, -1 if rh is None else rh, -1 if rw is None else rw, m)  # pyright: ignore[reportCallIssue] -- the unpacked tuple holds the other arguments
    assert resized_size((540, 960), ViewGeometry(resize_h=540, multiple=16)) == (544, 960)


def ramp_scene(rng, n, h, w):
    """Images that are a linear function of continuous pixel position (x, y), and depth
    constant on each pixel (a staircase in x), with random cameras."""
    coef = rng.uniform(0.2, 0.5, size=(3, 3))
    yy, xx = np.mgrid[0:h, 0:w] + 0.5
    img = np.stack([coef[c, 0] * xx / w + coef[c, 1] * yy / h + coef[c, 2] for c in range(3)], axis=-1)
    depth = 1.0 + np.floor(xx) * 0.01 + np.floor(yy) * 0.001
    angles = rng.uniform(0, 2 * np.pi, n)
    c2w = np.tile(np.eye(4), (n, 1, 1))
    c2w[:, 0, 0], c2w[:, 0, 2], c2w[:, 2, 0], c2w[:, 2, 2] = (
        np.cos(angles),
        np.sin(angles),
        -np.sin(angles),
        np.cos(angles),
    )
    c2w[:, :3, 3] = rng.normal(size=(n, 3))
    k = np.tile([[0.9 * w, 0.95 * w, 0.52 * w, 0.47 * h]], (n, 1))
    scene = in_memory_scene("ramp", np.tile(img[None], (n, 1, 1, 1)), c2w, k, np.tile(depth[None], (n, 1, 1)))
    return scene, coef


@pytest.mark.parametrize("square,zoom", [(False, 1.0), (True, 1.0), (True, 0.6), (False, 0.7)])
def test_sample_intrinsics_are_exact(rng, square, zoom):
    """Each output pixel centre maps back, through output and source intrinsics (same ray),
    to the source position whose ramp value the output holds."""
    h, w = 90, 120
    scene, coef = ramp_scene(rng, 5, h, w)
    geom = ViewGeometry(resize_h=48, multiple=8, square_crop=square, zoom_min=zoom)
    s = make_sample(scene, np.array([0, 2, 4]), np.array([1, 3]), geom, rng=rng, with_depth=True)
    oh, ow = output_size((h, w), geom)
    assert s["input_images"].shape == (3, oh, ow, 3) and s["target_depth"].shape == (2, oh, ow)
    k_src = scene.intrinsics[0]
    _, _, _, scale = normalize_scene(scene.c2w[[0, 2, 4]], scene.c2w[[1, 3]])
    for key_img, key_k in (("input_images", "input_intrinsics"), ("target_images", "target_intrinsics")):
        for v in range(s[key_img].shape[0]):
            k = s[key_k][v].astype(np.float64)
            yy, xx = np.mgrid[0:oh, 0:ow] + 0.5
            xs = k_src[2] + k_src[0] * (xx - k[2]) / k[0]
            ys = k_src[3] + k_src[1] * (yy - k[3]) / k[1]
            expect = np.stack([coef[c, 0] * xs / w + coef[c, 1] * ys / h + coef[c, 2] for c in range(3)], axis=-1)
            # interior: the anti-aliasing blur and border clamping only touch the edges
            np.testing.assert_allclose(s[key_img][v][3:-3, 3:-3], expect[3:-3, 3:-3], atol=2e-5)
            if key_img == "target_images":
                d_expect = (1.0 + np.floor(xs) * 0.01 + np.floor(ys) * 0.001) * scale
                err = np.abs(s["target_depth"][v] - d_expect)[3:-3, 3:-3]
                assert np.median(err) < 1e-6 and err.max() <= 0.0111 * scale  # at most one source pixel off


def test_crop_box():
    assert crop_box((60, 100), ViewGeometry(square_crop=True)) == (0, 20, 60, 60)
    assert crop_box((100, 60), ViewGeometry(square_crop=True)) == (20, 0, 60, 60)
    assert crop_box((60, 100), ViewGeometry()) == (0, 0, 60, 100)


def test_zoom_offset_is_long_lrm_centre_crop():
    """torch sizes the 1/r upsample floor(n / r); the crop starts at half the excess, floored."""
    for n, r in ((544, 0.77), (960, 0.77), (256, 0.9), (336, 0.999), (448, 1.0)):
        mag = int(np.floor(n * (1.0 / r)))
        assert zoom_offset((n, n), r) == ((mag - n) // 2,) * 2


def blob_scene(rng, n, h, w, sigma):
    """Frames looking at one 3-D point X (random cameras around it), each image a Gaussian
    blob of ``sigma`` px centred on X's projection, principal point well off-centre."""
    x_world = rng.normal(size=3)
    k = np.array([0.8 * w, 0.85 * w, 0.62 * w, 0.41 * h])
    c2w = np.tile(np.eye(4), (n, 1, 1))
    for i in range(n):
        a = rng.uniform(-0.3, 0.3)
        c2w[i, :3, :3] = [[np.cos(a), 0, np.sin(a)], [0, 1, 0], [-np.sin(a), 0, np.cos(a)]]
        cam = np.array([rng.uniform(-0.3, 0.3), rng.uniform(-0.2, 0.2), rng.uniform(2.0, 3.0)])
        c2w[i, :3, 3] = x_world - c2w[i, :3, :3] @ cam
    pix = project_points(np.tile(x_world, (n, 1, 1)), c2w, np.tile(k, (n, 1)))[0][:, 0]
    yy, xx = np.mgrid[0:h, 0:w] + 0.5
    img = np.stack([np.exp(-((xx - px) ** 2 + (yy - py) ** 2) / (2 * sigma**2)) for px, py in pix])
    return in_memory_scene("blob", np.repeat(img[..., None], 3, axis=-1), c2w, np.tile(k, (n, 1))), x_world


def centroid(img):
    yy, xx = np.mgrid[0 : img.shape[0], 0 : img.shape[1]] + 0.5
    return np.array([(img * xx).sum(), (img * yy).sum()]) / img.sum()


@pytest.mark.parametrize("r", [0.77, 0.83, 0.91, 1.0])
def test_zoom_keeps_projections_consistent(rng, r):
    """The zoomed view of a 3-D point sits where the zoomed intrinsics project it (blob
    centroid vs projection, <= 0.5 px; measured ~1e-3 px). Long-LRM's own rule
    (f * floor(W/r)/W, c unchanged) misses by > 1 px here: the principal point is off-centre."""
    h, w = 80, 112
    scene, x_world = blob_scene(rng, 3, h, w, sigma=2.5)
    box = crop_box((h, w), ViewGeometry())
    images, intr, _ = load_views(scene, np.arange(3), (h, w), box, None if r == 1.0 else r, False)
    for v in range(3):
        got = centroid(images[v][..., 0])
        want = project_points(x_world[None], scene.c2w[v], intr[v])[0][0]
        assert np.abs(got - want).max() <= 0.5, (got, want)
        assert np.abs(got - want).max() < 0.01
        if r < 1.0:
            k = scene.intrinsics[v]
            mag = np.floor(np.array([w, h]) / r)
            long_lrm = np.array([k[0] * mag[0] / w, k[1] * mag[1] / h, k[2], k[3]])
            assert np.abs(project_points(x_world[None], scene.c2w[v], long_lrm)[0][0] - got).max() > 1.0


def test_one_zoom_per_sample(rng):
    """Inputs and targets of a sample share r: every view's focal is the stored focal x
    (resize factor) / r with the same r, and r lies in [zoom_min, 1]."""
    scene, _ = ramp_scene(rng, 6, 90, 120)
    geom = ViewGeometry(resize_h=48, multiple=8, zoom_min=0.77)
    rs = []
    for seed in range(5):
        s = make_sample(scene, np.array([0, 2, 4]), np.array([1, 5]), geom, rng=np.random.default_rng(seed))
        ks = np.concatenate([s["input_intrinsics"], s["target_intrinsics"]])
        resize = 48 / 90
        r = scene.intrinsics[0, 0] * resize / ks[:, 0]
        np.testing.assert_allclose(r, r[0], rtol=1e-6)
        rs.append(r[0])
    assert all(0.77 <= r <= 1.0 for r in rs) and len(set(np.round(rs, 6))) == 5


def test_sample_is_normalised_and_depth_consistent():
    """Target depth, unprojected with the normalised target cameras, equals the normalised
    world points (the original unprojection mapped by the normalisation)."""
    scene = procedural_scene(4, ProceduralConfig(height=40, width=56, num_frames=10))
    inputs, targets = np.array([0, 3, 6, 9]), np.array([2, 5])
    s = make_sample(scene, inputs, targets, ViewGeometry(multiple=8), with_depth=True, scene_scale=1.35)
    np.testing.assert_allclose(np.abs(s["input_c2w"][:, :3, 3]).max(), 1 / 1.35, rtol=1e-6)
    np.testing.assert_allclose(s["input_c2w"][:, :3, 3].mean(0), 0, atol=1e-6)
    _, _, transform, scale = normalize_scene(scene.c2w[inputs], scene.c2w[targets], scene_scale=1.35)
    for v, f in enumerate(targets):
        world = unproject_depth(scene.depth(f).astype(np.float64), scene.c2w[f], scene.intrinsics[f])
        expect = world @ transform[:3, :3].T + transform[:3, 3]
        got = unproject_depth(
            s["target_depth"][v].astype(np.float64),
            s["target_c2w"][v].astype(np.float64),
            s["target_intrinsics"][v].astype(np.float64),
        )
        np.testing.assert_allclose(got, expect, atol=2e-4)


def test_depth_requested_without_depth():
    scene = in_memory_scene(
        "nodepth", np.zeros((3, 8, 8, 3)), np.tile(np.eye(4), (3, 1, 1)), np.tile([[8.0, 8, 4, 4]], (3, 1))
    )
    with pytest.raises(ValueError, match="'nodepth': depth requested but the scene has no depth"):
        make_sample(scene, np.array([0, 1]), np.array([2]), ViewGeometry(), with_depth=True)
