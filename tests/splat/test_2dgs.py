"""The 2DGS splatter (``rasterize(..., primitive="2dgs")``) against the brute-force float64
reference (``splat.reference_2dgs``: geometric ray-plane intersection, every pixel against
every surfel, no boxes) on fresh random posed scenes with tilted, edge-on and overlapping
surfels, forward (F=32 features, float64 and float32) and gradients (custom VJP vs the
reference's autodiff, and central finite differences, float64)."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from llrmpp_jax.splat import SplatConfig, rasterize
from llrmpp_jax.splat.reference_2dgs import render_surfels_reference

H, W = 27, 37
OUTPUTS = ("features", "transmittance", "depth", "normals", "median_depth", "distortion")


def _quat_wxyz(rot: np.ndarray) -> np.ndarray:
    return Rotation.from_matrix(rot).as_quat()[:, [3, 0, 1, 2]]


def surfel_scene(rng: np.random.Generator, f: int):
    """A posed scene: random tilted surfels, six within 2 degrees of edge-on, and a stack of
    six overlapping ones at one screen point. Returns (means, quats, scales, opac, feats, c2w, intr)."""
    intr = np.array([0.8 * W, 0.85 * W, 0.52 * W, 0.47 * H])
    n_tilted, n_edge, n_stack = 24, 6, 6
    n = n_tilted + n_edge + n_stack
    z = rng.uniform(1.5, 4.0, n)
    px = np.concatenate([rng.uniform(0.1 * W, 0.9 * W, n_tilted + n_edge), np.full(n_stack, 0.4 * W)])
    py = np.concatenate([rng.uniform(0.1 * H, 0.9 * H, n_tilted + n_edge), np.full(n_stack, 0.6 * H)])
    px[-n_stack:] += rng.uniform(-1.5, 1.5, n_stack)
    means_c = np.stack([(px - intr[2]) / intr[0] * z, (py - intr[3]) / intr[1] * z, z], -1)
    rot_c = Rotation.random(n, random_state=rng).as_matrix()  # pyright: ignore[reportCallIssue] -- scipy still takes random_state; its stubs name only rng
    for i in range(n_tilted, n_tilted + n_edge):  # normal within 2 degrees of perpendicular to the view ray
        ray = means_c[i] / np.linalg.norm(means_c[i])
        side = np.cross(ray, rng.normal(size=3))
        side /= np.linalg.norm(side)
        tilt = np.deg2rad(rng.uniform(-2.0, 2.0))
        normal = np.cos(tilt) * side + np.sin(tilt) * ray
        tu = np.cross(normal, rng.normal(size=3))
        tu /= np.linalg.norm(tu)
        rot_c[i] = np.stack([tu, np.cross(normal, tu), normal], axis=-1)
    c2w = np.eye(4)
    c2w[:3, :3], c2w[:3, 3] = Rotation.random(random_state=rng).as_matrix(), rng.normal(size=3)  # pyright: ignore[reportCallIssue] -- as above
    means = means_c @ c2w[:3, :3].T + c2w[:3, 3]
    quats = _quat_wxyz(c2w[:3, :3][None] @ rot_c) * rng.uniform(0.5, 2.0, (n, 1))  # unnormalised
    scales = np.exp(rng.uniform(np.log(0.02), np.log(0.4), (n, 2)))
    opac = rng.uniform(0.1, 0.9, n)
    feats = rng.normal(size=(n, f))
    return means, quats, scales, opac, feats, c2w, intr


def _render(scene, depth, dtype):
    m, q, s, o, f, c2w, intr = (jnp.asarray(x, dtype) for x in scene)
    return rasterize(m, q, s, o, f, c2w, intr, H, W, primitive="2dgs", surfel_depth=depth)


def _reference(scene, depth):
    m, q, s, o, f, c2w, intr = (jnp.asarray(x, jnp.float64) for x in scene)
    return render_surfels_reference(m, q, s, o, f, c2w, intr, H, W, depth=depth)


@pytest.mark.parametrize("depth", ["center", "intersection"])
def test_forward_matches_reference(rng, depth):
    """F=32 features, float64 to 1e-10 and float32 to 1e-3 (of the largest value) of the
    float64 reference."""
    scene = surfel_scene(rng, 32)
    ref = _reference(scene, depth)
    assert float(jnp.min(ref.transmittance)) < 0.2 and float(jnp.max(ref.distortion)) > 0.05  # overlaps matter
    for dtype, atol in ((jnp.float64, 1e-10), (jnp.float32, 1e-3)):
        out = _render(scene, depth, dtype)
        assert int(out.stats.num_visible) == len(scene[0]) and not bool(out.stats.overflow)
        for name in OUTPUTS:
            got, exp = np.asarray(getattr(out, name), np.float64), np.asarray(getattr(ref, name))
            scale = max(float(np.abs(exp).max()), 1.0)
            np.testing.assert_allclose(got, exp, rtol=0, atol=atol * scale, err_msg=f"{name} {dtype.__name__}")


def test_fronto_parallel_surfel_by_hand():
    """A surfel facing the camera centred on pixel (5, 7)'s ray: alpha = o there, normal
    (0, 0, -1) (the quaternion's +z flipped toward the camera), depth o z, median z, no
    distortion."""
    intr = np.array([30.0, 30.0, 12.0, 10.0])
    z, o = 2.0, 0.7
    means = np.array([[(5.5 - 12) / 30 * z, (7.5 - 10) / 30 * z, z]])
    scene = (means, np.array([[1.0, 0, 0, 0]]), np.array([[0.05, 0.08]]), np.array([o]), np.ones((1, 1)))
    scene = scene + (np.eye(4), intr)
    out = _render(scene, "intersection", jnp.float64)
    assert out.normals is not None and out.median_depth is not None and out.distortion is not None
    assert float(out.features[7, 5, 0]) == pytest.approx(o, abs=1e-12)
    np.testing.assert_allclose(np.asarray(out.normals[7, 5]), [0.0, 0.0, -o], atol=1e-12)
    assert float(out.depth[7, 5]) == pytest.approx(o * z, abs=1e-12)
    assert float(out.median_depth[7, 5]) == pytest.approx(z, abs=1e-12)
    assert float(out.distortion[7, 5]) == 0.0


def _loss(scene_args, camera, depth, cot, fast: bool):
    (m, q, s, o, f), (c2w, intr) = scene_args, camera
    if fast:
        cfg = SplatConfig(max_intersections=8192)
        out = rasterize(m, q, s, o, f, c2w, intr, H, W, cfg, primitive="2dgs", surfel_depth=depth)
        outs = [getattr(out, name) for name in OUTPUTS]
    else:
        outs = list(render_surfels_reference(m, q, s, o, f, c2w, intr, H, W, depth=depth))
    return sum(jnp.sum(x * g) for x, g in zip(outs, cot))


@pytest.mark.parametrize("depth", ["center", "intersection"])
def test_grads_match_reference_autodiff_and_finite_differences_float64(rng, depth):
    scene = surfel_scene(rng, 4)
    args = [jnp.asarray(x) for x in scene[:5]]
    camera = (jnp.asarray(scene[5]), jnp.asarray(scene[6]))
    shapes = ((H, W, 4), (H, W), (H, W), (H, W, 3), (H, W), (H, W))
    cot = [jnp.asarray(rng.normal(size=s)) for s in shapes]
    fast = jax.jit(lambda *a: _loss(a, camera, depth, cot, True))
    got = jax.jit(jax.grad(fast, argnums=tuple(range(5))))(*args)
    exp = jax.jit(jax.grad(lambda *a: _loss(a, camera, depth, cot, False), argnums=tuple(range(5))))(*args)
    names = ("means", "quats", "scales", "opacities", "features")
    for name, g, e in zip(names, got, exp):
        assert float(jnp.max(jnp.abs(e))) > 0, name
        np.testing.assert_allclose(
            np.asarray(g), np.asarray(e), rtol=1e-7, atol=1e-9 * float(jnp.abs(e).max()), err_msg=name
        )
    h = 1e-6
    for i, name in enumerate(names):  # directional derivatives along a random direction
        d = jnp.asarray(rng.normal(size=args[i].shape))
        plus, minus = list(args), list(args)
        plus[i], minus[i] = args[i] + h * d, args[i] - h * d
        fd = (float(fast(*plus)) - float(fast(*minus))) / (2 * h)
        analytic = float(jnp.sum(got[i] * d))
        assert fd == pytest.approx(analytic, rel=1e-5, abs=1e-6), name


def test_opacity_copies_match_separate_renders(rng):
    """[S, N] opacities render like S separate renders (one projection and binning)."""
    means, quats, scales, opac, feats, c2w, intr = surfel_scene(rng, 3)
    opac2 = np.stack([opac, rng.uniform(0.1, 0.9, len(opac))])
    both = _render((means, quats, scales, opac2, feats, c2w, intr), "center", jnp.float64)
    for s in range(2):
        one = _render((means, quats, scales, opac2[s], feats, c2w, intr), "center", jnp.float64)
        for name in OUTPUTS:
            np.testing.assert_allclose(np.asarray(getattr(both, name)[s]), np.asarray(getattr(one, name)), atol=1e-12)


def test_bad_2dgs_arguments_are_named(rng):
    means, quats, scales, opac, feats, c2w, intr = surfel_scene(rng, 3)
    three = np.concatenate([scales, scales[:, :1]], axis=1)
    with pytest.raises(ValueError, match=r"scales must have shape \(N, 2\) for primitive '2dgs'"):
        _render((means, quats, three, opac, feats, c2w, intr), "center", jnp.float64)
    with pytest.raises(ValueError, match="surfel_depth must be one of"):
        _render((means, quats, scales, opac, feats, c2w, intr), "centre", jnp.float64)
    with pytest.raises(ValueError, match="primitive must be one of"):
        rasterize(means, quats, scales, opac, feats, c2w, intr, H, W, primitive="3d")
