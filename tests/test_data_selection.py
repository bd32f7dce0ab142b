"""View selection: k-means inputs against brute force on separable clusters, the Lloyd
fixed point, the every-8th/k-means evaluation split, and the training draw's target
distribution against exact enumeration of weighted sampling without replacement."""

import itertools

import numpy as np
import pytest

from llrmpp_jax.data.camera_paths import look_at
from llrmpp_jax.data.selection import eval_views, every_nth, kmeans, kmeans_inputs, training_views, uniform_inputs


def cameras_from_features(pos, fwd):
    return look_at(pos, pos + fwd)


def test_kmeans_is_a_lloyd_fixed_point_and_deterministic(rng):
    pts = rng.normal(size=(60, 6))
    c1 = kmeans(pts, 7, seed=0)
    np.testing.assert_array_equal(c1, kmeans(pts, 7, seed=0))
    label = np.argmin(((pts[:, None] - c1[None]) ** 2).sum(-1), axis=1)
    for c in range(7):  # every centre is the mean of the points nearest to it
        np.testing.assert_allclose(c1[c], pts[label == c].mean(0), atol=1e-12)


def test_kmeans_inputs_find_one_frame_per_separated_cluster(rng):
    """Six tight groups of cameras far apart: exactly one input per group, and it is the
    group member nearest the group's mean feature (brute force)."""
    k, per = 6, 9
    centres = rng.uniform(-20, 20, size=(k, 3))
    pos = np.concatenate([c + 0.05 * rng.normal(size=(per, 3)) for c in centres])
    fwd = np.tile(np.array([[1.0, 0.2, 0.1]]), (k * per, 1)) + 0.05 * rng.normal(size=(k * per, 3))
    order = rng.permutation(k * per)
    pos, fwd = pos[order], fwd[order]
    c2w = cameras_from_features(pos, fwd)
    group = (np.arange(k * per) // per)[order]
    chosen = kmeans_inputs(c2w, np.arange(k * per), k)
    feats = np.concatenate([c2w[:, :3, 3], c2w[:, :3, 2]], axis=1)
    expect = []
    for g in range(k):
        members = np.flatnonzero(group == g)
        mean = feats[members].mean(0)
        expect.append(members[np.argmin(((feats[members] - mean) ** 2).sum(1))])
    np.testing.assert_array_equal(chosen, np.sort(expect))


def orbit_cameras(n):
    ang = np.linspace(0, 3 * np.pi, n)
    pos = np.stack([3 * np.cos(ang), 3 * np.sin(ang), 1 + 0.3 * np.sin(5 * ang)], axis=1)
    return look_at(pos, np.zeros((n, 3)))


@pytest.mark.parametrize("num_inputs", [4, 16, 32])
def test_eval_views_split(num_inputs):
    c2w = orbit_cameras(90)
    inputs, targets = eval_views(c2w, num_inputs, every=8)
    np.testing.assert_array_equal(targets, np.arange(0, 90, 8))
    assert len(inputs) == len(set(inputs.tolist())) == num_inputs
    assert not set(inputs.tolist()) & set(targets.tolist())
    assert (np.diff(inputs) > 0).all() and inputs.min() >= 0 and inputs.max() < 90
    again, _ = eval_views(c2w.copy(), num_inputs, every=8)
    np.testing.assert_array_equal(inputs, again)
    inputs_1280, targets_1280 = eval_views(c2w, 8, every=8, max_frames=40)
    assert targets_1280.max() < 40 and inputs_1280.max() < 40


def test_too_few_frames_is_an_error():
    c2w = orbit_cameras(20)
    with pytest.raises(ValueError, match=r"18 input views requested but only 17 candidate"):
        eval_views(c2w, 18, every=8)  # 20 frames - 3 targets = 17 candidates < 18
    with pytest.raises(ValueError, match=r"scene has 5 usable frames, fewer than the 6 views"):
        training_views(np.random.default_rng(0), 5, 6, 2)
    with pytest.raises(ValueError, match="8 views requested from 5"):
        uniform_inputs(5, 8)
    np.testing.assert_array_equal(every_nth(17, 8), [0, 8, 16])


def test_training_inputs_are_long_lrm_linspace(rng):
    for _ in range(20):
        inputs, targets = training_views(rng, 100, 8, 4, min_span=30, max_span=60)
        start, end = inputs[0], inputs[-1]
        assert 30 <= end - start <= 60
        np.testing.assert_array_equal(inputs, start + np.linspace(0, end - start, 8, dtype=int))
        assert len(set(targets.tolist())) == 4 and start <= targets.min() and targets.max() <= end


def test_training_targets_follow_weighted_sampling_without_replacement():
    """5 frames, inputs {0, 4} at weight 0.1, two targets: the frequency of every target pair
    matches sequential weighted draws without replacement (4 sigma)."""
    rng = np.random.default_rng(1234)
    draws = 3000
    counts = {}
    for _ in range(draws):
        inputs, targets = training_views(rng, 5, 2, 2, min_span=4, max_span=4, input_weight=0.1)
        np.testing.assert_array_equal(inputs, [0, 4])
        key = tuple(targets.tolist())
        counts[key] = counts.get(key, 0) + 1
    w = np.array([0.1, 1.0, 1.0, 1.0, 0.1])
    total = w.sum()
    for a, b in itertools.combinations(range(5), 2):
        p = w[a] / total * w[b] / (total - w[a]) + w[b] / total * w[a] / (total - w[b])
        got = counts.get((a, b), 0) / draws
        assert abs(got - p) < 4 * np.sqrt(p * (1 - p) / draws) + 1e-3, ((a, b), got, p)
