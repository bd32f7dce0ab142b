"""Gradients of ``rasterize`` (custom VJP of the compositor + autodiff of the projection).

Oracles: autodiff of the brute-force reference (``splat.reference``, a ``lax.scan`` over
depth-sorted Gaussians in gsplat's formulation) and central finite differences, both in
float64, on smooth scenes (``tests/helpers/smooth_splat.py``): every alpha at least 0.1 %
(relative) away from 1/255, no pixel near the 1e-4 transmittance stop, no alpha clamped, no
screen radius or tile box near an integer boundary, centres inside the field of view -- so
the piecewise rules cannot switch between the evaluation points (gsplat's tests stay away
from the same thresholds).
"""

import jax
import jax.numpy as jnp
import numpy as np
from scipy.spatial.transform import Rotation

from llrmpp_jax.splat import rasterize
from llrmpp_jax.splat.reference import render_features_reference
from tests.helpers.smooth_splat import F, H, W, smooth_scene, value_and_grad


def _cotangents(rng):
    return tuple(jnp.asarray(rng.normal(size=s)) for s in ((H, W, F), (H, W), (H, W)))


def test_grads_match_reference_autodiff_float64(rng):
    means, quats, scales, opac, feats, c2w, intr = smooth_scene(rng)
    cot = _cotangents(rng)
    args = [jnp.asarray(a) for a in (means, quats, scales, opac, feats)]
    camera = (jnp.asarray(c2w), jnp.asarray(intr))
    _, got = value_and_grad(*args, *camera, cot)

    def ref_loss(*a):
        out = render_features_reference(*a, jnp.asarray(c2w), jnp.asarray(intr), H, W)  # pyright: ignore[reportCallIssue] -- the unpacked tuple holds the other arguments
        return sum(jnp.sum(x * g) for x, g in zip(out, cot))

    exp = jax.jit(jax.grad(ref_loss, argnums=tuple(range(5))))(*args)
    for name, g, e in zip(("means", "quats", "scales", "opacities", "features"), got, exp):
        assert np.all(np.abs(e) > 0) or name == "quats"  # every Gaussian is seen
        np.testing.assert_allclose(np.asarray(g), np.asarray(e), rtol=1e-7, atol=1e-9 * np.abs(e).max(), err_msg=name)


def test_grads_match_finite_differences_float64(rng):
    means, quats, scales, opac, feats, c2w, intr = smooth_scene(rng)
    cot = _cotangents(rng)
    args = [jnp.asarray(a) for a in (means, quats, scales, opac, feats)]
    camera = (jnp.asarray(c2w), jnp.asarray(intr))
    _, grads = value_and_grad(*args, *camera, cot)
    h = 1e-6
    for i, name in enumerate(("means", "quats", "scales", "opacities", "features")):
        direction = rng.normal(size=args[i].shape)
        plus = [a + h * direction if j == i else a for j, a in enumerate(args)]
        minus = [a - h * direction if j == i else a for j, a in enumerate(args)]
        fd = (float(value_and_grad(*plus, *camera, cot)[0]) - float(value_and_grad(*minus, *camera, cot)[0])) / (2 * h)
        ad = float(jnp.sum(grads[i] * direction))
        assert abs(fd - ad) <= 1e-4 * abs(ad), (name, fd, ad)


def test_grads_float32_close_to_float64(rng):
    means, quats, scales, opac, feats, c2w, intr = smooth_scene(rng)
    cot = _cotangents(rng)
    camera = (jnp.asarray(c2w), jnp.asarray(intr))
    args64 = [jnp.asarray(np.asarray(a, np.float32), jnp.float64) for a in (means, quats, scales, opac, feats)]
    _, g64 = value_and_grad(*args64, *camera, cot)
    _, g32 = value_and_grad(*(a.astype(jnp.float32) for a in args64), *camera, cot)
    for name, a, b in zip(("means", "quats", "scales", "opacities", "features"), g32, g64):
        assert a.dtype == jnp.float32
        rel = float(jnp.linalg.norm((a.astype(jnp.float64) - b).ravel()) / jnp.linalg.norm(b.ravel()))
        assert rel < 1e-4, (name, rel)


def test_value_and_grad_value_matches_forward_and_reference_at_16k_gaussians(rng):
    """The loss inside ``value_and_grad`` w.r.t. means equals a plain jitted forward pass
    and the brute-force reference, in float32, with N = 16384 Gaussians (most behind the
    camera, some at Long-LRM's 0.3 scale clamp). jaxlib 0.10.2's CPU compiler miscompiled
    the projection's camera transform at this N (jax-ml/jax#39103): the last third of the
    Gaussians took the position of the one 42 rows earlier, differently in each program,
    so the two losses disagreed (by 2-10 % on the golden fox scene)."""
    n, h, w, f = 16384, 16, 16, 3
    intr = np.array([0.8 * w, 0.8 * w, 0.5 * w, 0.5 * h])
    z = rng.uniform(-2.0, 0.0, n)  # behind the camera: culled
    front = rng.random(n) < 0.2
    z[front] = rng.uniform(1.0, 6.0, int(front.sum()))
    u, v = rng.uniform(-0.1 * w, 1.1 * w, n), rng.uniform(-0.1 * h, 1.1 * h, n)
    means_c = np.stack([(u - intr[2]) / intr[0] * z, (v - intr[3]) / intr[1] * z, z], -1)
    c2w = np.eye(4)
    c2w[:3, :3], c2w[:3, 3] = Rotation.random(random_state=rng).as_matrix(), rng.normal(size=3)  # pyright: ignore[reportCallIssue] -- scipy still takes random_state; its stubs name only rng
    means = means_c @ c2w[:3, :3].T + c2w[:3, 3]
    scales = np.exp(rng.uniform(-5.0, -2.5, (n, 3)))
    scales[rng.random((n, 3)) < 0.1] = 0.3
    scene32 = [
        jnp.asarray(a, jnp.float32)
        for a in (means, rng.normal(size=(n, 4)), scales, rng.uniform(0.05, 0.9, n), rng.normal(size=(n, f)), c2w, intr)
    ]
    cot = [jnp.asarray(rng.normal(size=s), jnp.float32) for s in ((h, w, f), (h, w), (h, w))]

    def loss(means, quats, scales, opac, feats, c2w, intr):
        out = rasterize(means, quats, scales, opac, feats, c2w, intr, h, w)
        return sum(jnp.sum(x * g) for x, g in zip(out[:3], cot))

    def ref_loss(*scene):
        out = render_features_reference(*(a.astype(jnp.float64) for a in scene), h, w)  # pyright: ignore[reportCallIssue] -- the unpacked tuple holds the other arguments
        return sum(jnp.sum(x * g.astype(jnp.float64)) for x, g in zip(out, cot))

    plain = float(jax.jit(loss)(*scene32))
    with_grad, _ = jax.jit(jax.value_and_grad(loss))(*scene32)
    expected = float(jax.jit(ref_loss)(*scene32))
    scale = float(sum(jnp.sum(jnp.abs(g)) for g in cot))  # |loss| <= scale * max |output|
    assert abs(float(with_grad) - plain) <= 1e-6 * scale, (float(with_grad), plain)
    assert abs(plain - expected) <= 1e-6 * scale, (plain, expected)
