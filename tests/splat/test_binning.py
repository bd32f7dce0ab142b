"""Tile binning against the oracle's per-tile lists (built by plain loops), overflow, sizing."""

import functools

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from llrmpp_jax.splat import SplatConfig
from llrmpp_jax.splat.binning import bin_gaussians, depth_order, depth_positions, intersection_counts
from llrmpp_jax.splat.projection import project_gaussians
from tests.oracles.splat import BLOCK, oracle_block_reached, oracle_project, oracle_tile_lists, random_scene

H, W, N = 37, 53, 300


@functools.partial(jax.jit, static_argnames=("capacity",))
def _bin(means, quats, scales, c2w, intr, capacity, opacities=None):
    proj = project_gaussians(means, quats, scales, c2w, intr, H, W)
    return bin_gaussians(proj, H, W, capacity, SplatConfig(), opacities)


@functools.partial(jax.jit, static_argnames=("height", "width"))
def _count(means, quats, scales, c2w, intr, height=H, width=W, opacities=None):
    """Slots the buffer needs: the sum of the per-Gaussian block counts."""
    proj = project_gaussians(means, quats, scales, c2w, intr, height, width)
    return jnp.sum(intersection_counts(proj, height, width, SplatConfig(), opacities))


def _lists(bins):
    ids, start, count = (np.asarray(a) for a in (bins.gaussian_ids, bins.tile_start, bins.tile_count))
    return [ids[s : s + c].tolist() for s, c in zip(start, count)]


def _scene(rng):
    means, quats, scales, _, _, c2w, intr = random_scene(rng, N, 1, H, W)
    # Equal depths for a few Gaussians: ties must resolve by index (a stable sort).
    means[10:14] = means[10]
    return means, quats, scales, c2w, intr


def test_tile_lists_match_oracle(rng):
    scene = _scene(rng)
    expected, needed = oracle_tile_lists(oracle_project(*scene, H, W), H, W, block=BLOCK)
    bins = _bin(*(jnp.asarray(a) for a in scene), capacity=16 * N)
    assert _lists(bins) == expected
    assert int(bins.num_intersections) == needed and not bool(bins.overflow)
    assert int(bins.num_dropped) == 0
    assert int(_count(*scene)) == needed


def test_opacity_trimmed_lists_keep_every_block_a_pixel_needs(rng):
    """With opacities, a Gaussian's list entries are the blocks of its opacity-trimmed box
    (the oracle's boxes) that its ellipse ``alpha >= 1/255`` reaches: in depth order, a
    subset of the box's entries, and a superset of the blocks where a pixel centre reaches
    1/255 by brute force. The buffer demand stays the box count."""
    scene = _scene(rng)
    opac = rng.uniform(0.0, 1.0, N) ** 2  # mostly faint, a few below 1/255
    proj = oracle_project(*scene, H, W)
    full, needed_full = oracle_tile_lists(proj, H, W, block=BLOCK)
    boxed, needed = oracle_tile_lists(proj, H, W, opacities=opac, block=BLOCK)
    bins = _bin(*(jnp.asarray(a) for a in scene), capacity=16 * N, opacities=jnp.asarray(opac, jnp.float32))
    ours = _lists(bins)
    blocks_x = -(-W // BLOCK)
    for t, (box, got) in enumerate(zip(boxed, ours)):
        assert got == [g for g in box if g in set(got)], t  # a subset, in the box list's order
        reached = [g for g in box if oracle_block_reached(proj, opac, g, t % blocks_x, t // blocks_x, H, W)]
        assert set(reached) <= set(got), (t, sorted(set(reached) - set(got)))
    kept = sum(map(len, ours))
    assert kept < 0.9 * needed, (kept, needed)  # the ellipse test removes real work
    assert int(bins.num_intersections) == needed and not bool(bins.overflow)
    assert needed < 0.9 * needed_full  # the box trim removes real work on faint Gaussians
    assert all(set(t) <= set(f) for t, f in zip(boxed, full))  # it only removes entries
    assert int(_count(*scene)) == needed_full  # the bound without opacities
    assert int(_count(*scene, opacities=opac)) == needed  # the box count with them


def test_overflow_is_reported_and_keeps_nearest(rng):
    scene = _scene(rng)
    _, needed = oracle_tile_lists(oracle_project(*scene, H, W), H, W, block=BLOCK)
    capacity = needed // 2
    expected, _ = oracle_tile_lists(oracle_project(*scene, H, W), H, W, capacity=capacity, block=BLOCK)
    bins = _bin(*(jnp.asarray(a) for a in scene), capacity=capacity)
    assert bool(bins.overflow)
    assert int(bins.num_intersections) == needed
    assert int(bins.num_dropped) == needed - capacity
    assert _lists(bins) == expected  # the farthest Gaussians' entries are the ones dropped
    assert sum(len(x) for x in expected) == capacity


def test_default_capacity_holds_at_paper_density(rng):
    """Long-LRM++ density: 32 Gaussians per canvas pixel (4.2M on 272x480), here on a
    68x120 canvas (1/4 per side) with 261,120 Gaussians, every one inside the frustum
    (the worst case: all inputs see what the target sees), footprints (projected sigma)
    log-uniform in [0.25, 4] canvas pixels around the ~0.5 px a token's 16 Gaussians have."""
    height, width = 68, 120
    n = 32 * height * width
    fx = fy = 100.0
    intr = np.array([fx, fy, width / 2, height / 2])
    z = rng.uniform(1.0, 6.0, n)
    u, v = rng.uniform(0, width, n), rng.uniform(0, height, n)
    means = np.stack([(u - intr[2]) / fx * z, (v - intr[3]) / fy * z, z], -1)
    sigma_px = np.exp(rng.uniform(np.log(0.25), np.log(4.0), (n, 1)))
    scales = sigma_px * z[:, None] / fx * np.exp(rng.uniform(-1.0, 0.0, (n, 3)))
    quats = rng.normal(size=(n, 4))
    cfg = SplatConfig()
    # Every Gaussian as opaque as it can be: the most blocks a render can fill.
    opaque = np.full(n, cfg.alpha_max, np.float32)
    scene = [a.astype(np.float32) for a in (means, quats, scales, np.eye(4), intr)]
    needed = int(_count(*scene, height, width, opacities=opaque))
    capacity = cfg.capacity(n, height, width)
    print(f"paper density: {n} Gaussians need {needed} slots ({needed / n:.2f} each), capacity {capacity}")
    assert n < needed < capacity / 2, (needed, capacity)
    assert needed < int(_count(*scene, height, width))  # the bound without opacities


@pytest.mark.parametrize("ties", [False, True])
def test_depth_order_is_a_stable_argsort_with_undrawn_last(rng, ties):
    """Against NumPy's stable lexsort (drawn first, then depth, then index), alone and under
    vmap; with ties (a group of 41 equal depths and many pairs) ranked by index. The
    positions are the oracle order's inverse."""
    n = 2000
    depths = rng.uniform(0.02, 50.0, (3, n)).astype(np.float32)
    if ties:
        depths[:, 100:140] = depths[:, 7:8]
        depths[:, 1000:1500:2] = depths[:, 1001:1501:2]
    drawn = rng.uniform(size=(3, n)) < 0.8

    def oracle(d, m):
        return np.lexsort((np.arange(n), np.where(m, d, np.inf), ~m))

    got = jax.jit(jax.vmap(depth_order))(jnp.asarray(depths), jnp.asarray(drawn))
    for b in range(3):
        np.testing.assert_array_equal(np.asarray(got[b]), oracle(depths[b], drawn[b]))
        np.testing.assert_array_equal(
            np.asarray(depth_order(jnp.asarray(depths[b]), jnp.asarray(drawn[b]))), oracle(depths[b], drawn[b])
        )
        want = oracle(depths[b], drawn[b])
        inverse = np.empty(n, np.int64)
        inverse[want] = np.arange(n)
        for d in (depths[b], depths[b].astype(np.float64)):  # the key sort and the argsort
            order, position = depth_positions(jnp.asarray(d), jnp.asarray(drawn[b]))
            np.testing.assert_array_equal(np.asarray(order), want)
            np.testing.assert_array_equal(np.asarray(position), inverse)
