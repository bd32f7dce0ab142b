"""Entry-point behaviour: vmap over cameras, overflow, masking under jit, eager bad-input errors,
the buffer's sizing and the render modes."""

import dataclasses
import re

import jax
import numpy as np
import pytest

from llrmpp_jax.splat import SplatConfig, rasterize
from tests.helpers.typechecks import unchecked
from tests.oracles.splat import (
    BLOCK,
    assert_render_close,
    oracle_project,
    oracle_render,
    oracle_tile_lists,
    random_scene,
)

H, W, N, F = 37, 53, 300, 3


def test_vmap_over_cameras_equals_separate_renders(rng):
    scenes = [random_scene(np.random.default_rng(rng.integers(2**31)), N, F, H, W) for _ in range(3)]
    means, quats, scales, opac, feats = scenes[0][:5]
    c2ws = np.stack([s[5] for s in scenes])
    intrs = np.stack([s[6] for s in scenes])
    batched = jax.jit(jax.vmap(lambda c, k: rasterize(means, quats, scales, opac, feats, c, k, H, W)))(c2ws, intrs)
    for i in range(3):
        single = rasterize(means, quats, scales, opac, feats, c2ws[i], intrs[i], H, W)
        assert_render_close([x[i] for x in batched[:3]], single, atol=1e-12)
        assert int(batched.stats.num_intersections[i]) == int(single.stats.num_intersections)


def test_overflow_renders_the_nearest_entries_and_reports(rng):
    scene = random_scene(rng, N, F, H, W)
    _, needed = oracle_tile_lists(oracle_project(*scene[:3], *scene[5:], H, W), H, W, opacities=scene[3], block=BLOCK)
    capacity = needed // 3
    cfg = SplatConfig(max_intersections=capacity)
    out = rasterize(*scene, H, W, cfg)
    assert bool(out.stats.overflow)
    assert int(out.stats.capacity) == capacity and int(out.stats.num_intersections) == needed
    assert int(out.stats.num_dropped) == needed - capacity
    assert_render_close(out, oracle_render(*scene, H, W, capacity=capacity), atol=1e-8)


def test_nonfinite_gaussians_and_bad_camera_are_masked_under_jit(rng):
    means, quats, scales, opac, feats, c2w, intr = random_scene(rng, N, F, H, W)
    bad = dict(means=0, quats=1, scales=2, opac=3, feats=4)
    arrays = dict(means=means.copy(), quats=quats.copy(), scales=scales.copy(), opac=opac.copy(), feats=feats.copy())
    arrays["means"][0, 1] = np.nan
    arrays["quats"][1, 0] = np.inf
    arrays["scales"][2, 2] = -np.inf
    arrays["opac"][3] = np.nan
    arrays["feats"][4, 0] = np.inf
    jitted = jax.jit(rasterize, static_argnums=(7, 8))
    names = ("means", "quats", "scales", "opac", "feats")
    out = jitted(*(arrays[k] for k in names), c2w, intr, H, W)
    keep = np.ones(N, bool)
    keep[list(bad.values())] = False
    expected = oracle_render(means[keep], quats[keep], scales[keep], opac[keep], feats[keep], c2w, intr, H, W)
    assert_render_close(out, expected, atol=1e-8)
    assert int(out.stats.num_nonfinite) == 5 and not bool(out.stats.invalid_camera)

    for k in ([0.0, 40.0, 26.0, 18.0], [40.0, -3.0, 26.0, 18.0], [40.0, 40.0, np.inf, 18.0]):
        empty = jitted(means, quats, scales, opac, feats, c2w, np.asarray(k), H, W)
        assert bool(empty.stats.invalid_camera) and int(empty.stats.num_visible) == 0
        assert_render_close(empty, (np.zeros((H, W, F)), np.ones((H, W)), np.zeros((H, W))), atol=0)


def test_eager_bad_input_raises(rng):
    means, quats, scales, opac, feats, c2w, intr = random_scene(rng, 20, F, H, W)
    args = dict(means=means, quats=quats, scales=scales, opacities=opac, features=feats, c2w=c2w, intrinsics=intr)

    def call(**changes):
        return rasterize(**{**args, **changes}, height=H, width=W)

    for name in ("means", "scales", "opacities", "quats", "features"):
        x = args[name].copy()
        x.reshape(-1)[3] = np.nan
        with pytest.raises(ValueError, match=f"{name} has 1 non-finite"):
            call(**{name: x})
    with pytest.raises(ValueError, match=re.escape("fx, fy > 0")):
        call(intrinsics=np.array([0.0, 30.0, 10.0, 10.0]))
    with (
        pytest.raises(ValueError, match=re.escape("scales has N=19 Gaussians (shape (19, 3)) but means has N=20")),
        unchecked(),
    ):
        call(scales=scales[:19])
    with pytest.raises(ValueError, match=re.escape("quats must have shape (N, 4), got (20, 3)")), unchecked():
        call(quats=quats[:, :3])
    with pytest.raises(ValueError, match=re.escape("c2w must have shape (4, 4), got (3, 4)")), unchecked():
        call(c2w=c2w[:3])
    with pytest.raises(ValueError, match="height and width must be >= 1"):
        rasterize(**args, height=0, width=W)  # pyright: ignore[reportArgumentType] -- args are the arrays' keywords, not cfg
    with pytest.raises(ValueError, match="max_intersections"):
        dataclasses.replace(SplatConfig(), max_intersections=0)


def _next_size(needed):
    """The oracle of the capacity's rounding: the smallest ``m 2^e`` (``m`` in 8..15) or
    size below 8 that holds ``needed``."""
    return min(x for x in {m << e for m in range(8, 16) for e in range(0, 24)} | set(range(1, 8)) if x >= needed)


def test_capacity_rounds_to_the_next_size_of_eight_to_fifteen_times_a_power_of_two():
    from llrmpp_jax.splat.render import _round_capacity

    for needed in [1, 7, 8, 9, 15, 16, 17, 100, 1000, 4097, 123457, 2**20 + 1]:
        want = _next_size(needed)
        assert _round_capacity(needed) == want, needed
        assert want < needed * 1.125 + 1


def test_eager_render_fits_its_buffer_to_the_scene(rng):
    """Called eagerly with the default config, the buffer is sized from the exact count
    (the oracle's box count): no overflow, and the same canvas as a jitted render with the
    default capacity."""
    scene = random_scene(rng, N, F, H, W)
    _, needed = oracle_tile_lists(oracle_project(*scene[:3], *scene[5:], H, W), H, W, opacities=scene[3], block=BLOCK)
    out = rasterize(*scene, H, W)
    assert int(out.stats.num_intersections) == needed and not bool(out.stats.overflow)
    assert int(out.stats.capacity) == _next_size(needed) < SplatConfig().capacity(N, H, W)
    jitted = jax.jit(rasterize, static_argnums=(7, 8))(*scene, H, W)
    assert int(jitted.stats.capacity) == SplatConfig().capacity(N, H, W)
    assert_render_close(out[:3], jitted[:3], atol=1e-12)


def test_fit_capacity_takes_the_most_any_camera_needs_with_headroom(rng):
    """Over B=2 scenes x T=3 cameras (the scene's own, zoomed out x0.6, and one with
    nothing in front of it), with S=2 opacity copies: ``headroom`` x the largest oracle box count (of the most
    opaque copy), rounded up, and at least ``minimum``; a config that sets the capacity
    keeps it."""
    from llrmpp_jax.splat import fit_capacity

    scenes = [random_scene(np.random.default_rng(rng.integers(2**31)), N, F, H, W) for _ in range(2)]

    def away(c2w):  # 100 units ahead: every Gaussian behind it
        moved = c2w.copy()
        moved[:3, 3] += 100.0 * c2w[:3, 2]
        return moved

    c2w = np.stack([np.stack([s[5], s[5], away(s[5])]) for s in scenes])  # [B, T, 4, 4]
    intr = np.stack([np.stack([s[6], s[6] * [0.6, 0.6, 1.0, 1.0], s[6]]) for s in scenes])
    copies = [np.stack([s[3] * rng.uniform(0, 1, N), s[3]]) for s in scenes]
    counts = [
        [
            oracle_tile_lists(oracle_project(*s[:3], c2w[b, t], intr[b, t], H, W), H, W, opacities=s[3], block=BLOCK)[1]
            for t in range(3)
        ]
        for b, s in enumerate(scenes)
    ]
    assert counts[0][2] == counts[1][2] == 0 and len({c for row in counts for c in row[:2]}) == 4
    stack = [np.stack([s[i] for s in scenes]) for i in range(3)]
    got = fit_capacity(*stack, np.stack(copies), c2w, intr, H, W, headroom=1.3)  # pyright: ignore[reportCallIssue] -- the unpacked tuple holds the other arguments
    assert got.max_intersections == _next_size(int(np.ceil(1.3 * np.max(counts))))
    one = fit_capacity(*scenes[1][:3], copies[1], c2w[1], intr[1], H, W)
    assert one.max_intersections == _next_size(max(counts[1]))
    assert fit_capacity(*scenes[1][:3], copies[1], c2w[1], intr[1], H, W, minimum=10**6).max_intersections == 10**6
    fixed = SplatConfig(max_intersections=77)
    assert fit_capacity(*scenes[0][:3], copies[0], c2w[0], intr[0], H, W, fixed) is fixed


def test_expected_depth_mode_is_the_oracles_depth_over_alpha(rng):
    """gsplat's "ED" mode against the float64 oracle: accumulated z / accumulated alpha where
    anything was drawn (alpha >= 1/255 there), 0 elsewhere; part of the canvas left empty.
    "F+ED" gives the same depth next to the features, "D" the accumulated z alone; a
    background is composited under the features."""
    n = 20  # small Gaussians in front of an identity camera: most of the canvas stays empty
    z = rng.uniform(2.0, 4.0, n)
    means = np.stack([rng.uniform(-0.4, 0.4, n) * z, rng.uniform(-0.3, 0.3, n) * z, z], -1)
    scene = [
        means,
        rng.normal(size=(n, 4)),
        rng.uniform(0.02, 0.06, (n, 3)),
        rng.uniform(0.05, 1.0, n),
        rng.normal(size=(n, F)),
        np.eye(4),
        np.array([40.0, 40.0, W / 2, H / 2]),
    ]
    feats, trans, depth = oracle_render(*scene, H, W)  # pyright: ignore[reportCallIssue] -- the unpacked tuple holds the other arguments
    alpha = 1.0 - trans
    drawn = alpha > 0
    assert 0 < drawn.mean() < 1 and alpha[drawn].min() >= 1.0 / 255.0 - 1e-12
    want = np.where(drawn, depth / np.where(drawn, alpha, 1.0), 0.0)
    geometry = (*scene[:4], None, *scene[5:])
    ed = rasterize(*geometry, H, W, render_mode="ED")  # pyright: ignore[reportCallIssue] -- the unpacked tuple holds the other arguments
    np.testing.assert_allclose(np.asarray(ed.depth), want, rtol=1e-9, atol=1e-9)
    assert ed.features.shape == (H, W, 0)
    both = rasterize(*scene, H, W, render_mode="F+ED")  # pyright: ignore[reportCallIssue] -- the unpacked tuple holds the other arguments
    np.testing.assert_allclose(np.asarray(both.depth), want, rtol=1e-9, atol=1e-9)
    np.testing.assert_allclose(np.asarray(both.features), feats, atol=1e-9)
    np.testing.assert_allclose(np.asarray(rasterize(*geometry, H, W, render_mode="D").depth), depth, atol=1e-9)  # pyright: ignore[reportCallIssue] -- the unpacked tuple holds the other arguments
    background = rng.normal(size=F)
    under = rasterize(*scene, H, W, background=background)  # pyright: ignore[reportCallIssue] -- the unpacked tuple holds the other arguments
    np.testing.assert_allclose(np.asarray(under.features), feats + trans[..., None] * background, atol=1e-9)


def test_render_mode_arguments_are_checked(rng):
    scene = random_scene(rng, 20, F, H, W)
    geometry = (*scene[:4], None, *scene[5:])
    with pytest.raises(ValueError, match="render_mode must be one of"):
        rasterize(*scene, H, W, render_mode="RGBD")
    with pytest.raises(ValueError, match="renders depth only"):
        rasterize(*scene, H, W, render_mode="ED")
    with pytest.raises(ValueError, match="sh_degree is for the 'RGB'"):
        rasterize(*scene, H, W, sh_degree=1)
    with pytest.raises(ValueError, match=re.escape(f"background must have shape ({F},)")):
        rasterize(*scene, H, W, background=np.ones(F + 1))
    with pytest.raises(ValueError, match="needs features"):
        rasterize(*geometry, H, W)
