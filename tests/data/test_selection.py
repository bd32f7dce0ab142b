"""View selection: k-means inputs against scikit-learn called with Long-LRM's settings on
the fox and beer captures and random camera paths, and against brute force on separable
clusters; the every-8th/k-means and ScanNet evaluation splits (with cached indices and short
scenes); the training draw's target distribution against exact enumeration of weighted
sampling without replacement."""

import itertools
import json
import os
import warnings

import numpy as np
import pytest
from sklearn.cluster import KMeans

from llrmpp_jax.data.camera_paths import look_at
from llrmpp_jax.data.formats import read_colmap_scene, read_long_lrm_scene, read_nerfstudio_scene, write_long_lrm_scene
from llrmpp_jax.data.held_out import eval_split
from llrmpp_jax.data.scene import in_memory_scene
from llrmpp_jax.data.selection import eval_views, every_nth, kmeans_inputs, training_views, uniform_inputs
from tests.helpers.environment import shared_path


def cameras_from_features(pos, fwd):
    return look_at(pos, pos + fwd)


def official_kmeans_split(positions, forwards, num_inputs, every=8):
    """Long-LRM's evaluation split written out here: targets every 8th frame, k-means
    (scikit-learn, random_state=0, n_init="auto") on [position, forward] of the others,
    the nearest frame per centre, sorted, no de-duplication."""
    frames = list(range(len(positions)))
    targets = list(range(0, len(frames), every))
    rest = [f for f in frames if f not in targets]
    feats = np.concatenate([positions[rest], forwards[rest]], axis=1)
    centres = KMeans(n_clusters=num_inputs, random_state=0, n_init="auto").fit(feats).cluster_centers_
    return sorted(rest[int(np.argmin(np.linalg.norm(feats - c, axis=1)))] for c in centres), targets


def fox_cameras():
    """Positions and forward axes straight from transforms.json (OpenGL: forward = -z), for
    the frames whose image exists, plus the same scene through the reader."""
    root = shared_path("data", "fox")
    meta = json.load(open(os.path.join(root, "transforms.json")))
    mats = np.array(
        [f["transform_matrix"] for f in meta["frames"] if os.path.exists(os.path.join(root, f["file_path"]))]
    )
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # 17 images are missing on purpose
        scene = read_nerfstudio_scene(root)
    return mats[:, :3, 3], -mats[:, :3, 2], scene.c2w


def beer_cameras():
    scene = read_colmap_scene(shared_path("data", "beer", "sparse", "0"), shared_path("data", "beer", "images"))
    return scene.c2w[:, :3, 3], scene.c2w[:, :3, 2], scene.c2w


def random_path_cameras(seed, n=120):
    rng = np.random.default_rng(seed)
    pos = np.cumsum(rng.normal(scale=0.3, size=(n, 3)), axis=0) * rng.uniform(0.1, 10.0)
    c2w = look_at(pos, pos + rng.normal(size=(n, 3)) + np.array([5.0, 0.0, 0.0]))
    return c2w[:, :3, 3], c2w[:, :3, 2], c2w


@pytest.mark.parametrize("cameras", ["fox", "beer", "random0", "random1", "random2"])
@pytest.mark.parametrize("num_inputs", [4, 16, 32])
def test_kmeans_inputs_equal_official_sklearn(cameras, num_inputs):
    pos, fwd, c2w = {"fox": fox_cameras, "beer": beer_cameras}.get(
        cameras, lambda: random_path_cameras(int(cameras[-1]))
    )()
    if num_inputs > len(pos) - len(range(0, len(pos), 8)):
        pytest.skip("fewer candidate frames than inputs")
    want_inputs, want_targets = official_kmeans_split(pos, fwd, num_inputs)
    inputs, targets = eval_views(c2w, num_inputs, every=8)
    np.testing.assert_array_equal(targets, want_targets)
    np.testing.assert_array_equal(inputs, want_inputs)


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
    assert len(inputs) == num_inputs and not set(inputs.tolist()) & set(targets.tolist())
    assert (np.diff(inputs) >= 0).all() and inputs.min() >= 0 and inputs.max() < 90
    inputs_40, targets_40 = eval_views(c2w, 8, every=8, max_frames=40)
    assert targets_40.max() < 40 and inputs_40.max() < 40


def long_lrm_uniform_rule(num_frames, num_inputs=128, every=8, first=1280):
    """Long-LRM's Dataset code for ``uniform_every`` targets and ``uniform`` inputs, over
    the first ``first`` frames (the paper's ScanNet protocol), transcribed."""
    frame_idx = list(range(min(first, num_frames)))
    target_idx = list(range(0, len(frame_idx), every))
    frame_idx = [x for x in frame_idx if x not in target_idx]
    input_idx = [frame_idx[i] for i in np.linspace(0, len(frame_idx) - 1, num_inputs, dtype=int)]
    return input_idx, target_idx


def synthetic_scene(n, rng):
    pos = np.cumsum(rng.normal(scale=0.05, size=(n, 3)), axis=0)
    c2w = look_at(pos, pos + np.array([1.0, 0.2, 0.1]))
    return in_memory_scene("seq", np.zeros((n, 8, 8, 3)), c2w, np.tile([[8.0, 8.0, 4.0, 4.0]], (n, 1)))


def test_scannet_split_on_a_1500_frame_sequence(rng):
    scene = synthetic_scene(1500, rng)
    inputs, targets, how = eval_split(scene, 128, "uniform", max_frames=1280)
    want_inputs, want_targets = long_lrm_uniform_rule(1500)
    np.testing.assert_array_equal(inputs, want_inputs)
    np.testing.assert_array_equal(targets, want_targets)
    assert len(targets) == 160 and inputs.max() < 1280 and len(set(inputs.tolist())) == 128
    assert how == "targets every 8th of the first 1280 frames, 128 inputs spread uniformly over the other 1120"


def test_scannet_split_of_a_short_scene_says_what_it_uses(rng):
    inputs, targets, how = eval_split(synthetic_scene(900, rng), 128, "uniform", max_frames=1280)
    want_inputs, want_targets = long_lrm_uniform_rule(900)
    np.testing.assert_array_equal(inputs, want_inputs)
    np.testing.assert_array_equal(targets, want_targets)
    assert how == (
        "only 900 frames, fewer than 1280: targets every 8th of all 900 frames, "
        "128 inputs spread uniformly over the other 787"
    )


def test_cached_kmeans_indices_are_used_and_checked(tmp_path, rng):
    """A Long-LRM scene JSON carrying 'fold_8_kmeans_4_input' is split with those indices;
    without the key the official k-means runs; an out-of-range index is one clear line."""
    scene = synthetic_scene(40, rng)
    path = write_long_lrm_scene(scene, str(tmp_path / "s"), image_ext=".png", bits=8)
    read = read_long_lrm_scene(path)
    inputs, targets, how = eval_split(read, 4, json_path=path)
    assert "k-means" in how
    np.testing.assert_array_equal(inputs, official_kmeans_split(read.c2w[:, :3, 3], read.c2w[:, :3, 2], 4)[0])
    meta = json.load(open(path))
    meta["fold_8_kmeans_4_input"] = [33, 2, 5, 9]
    json.dump(meta, open(path, "w"))
    inputs, targets, how = eval_split(read, 4, json_path=path)
    np.testing.assert_array_equal(inputs, [2, 5, 9, 33])
    np.testing.assert_array_equal(targets, np.arange(0, 40, 8))
    assert how == "inputs: the scene JSON's cached 'fold_8_kmeans_4_input'"
    meta["fold_8_kmeans_4_input"] = [1, 2, 40, 9]
    json.dump(meta, open(path, "w"))
    with pytest.raises(
        ValueError, match=r"'fold_8_kmeans_4_input' holds frame index 40, out of range for a scene of 40"
    ):
        eval_split(read, 4, json_path=path)


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


def test_long_lrm_kmeans_index_file(tmp_path, rng):
    """Long-LRM's dl3dv_fold_8_kmeans_input_idx.json layout (a list of per-scene entries):
    the scene's entry is used when its JSON has no cached key; other scenes fall back to the
    official k-means; an index past the scene's end is one clear line."""
    from llrmpp_jax.data.formats import read_kmeans_index

    scene = synthetic_scene(40, rng)
    index_path = str(tmp_path / "idx.json")
    json.dump(
        [
            {"scene_name": "seq", "fold_8_kmeans_4_input": [30, 3, 12, 20], "fold_8_kmeans_2_input": [1, 2]},
            {"scene_name": "other", "fold_8_kmeans_4_input": [1, 2, 3, 4]},
        ],
        open(index_path, "w"),
    )
    index = read_kmeans_index(index_path)
    inputs, targets, how = eval_split(scene, 4, index=index, index_name=index_path)
    np.testing.assert_array_equal(inputs, [3, 12, 20, 30])
    np.testing.assert_array_equal(targets, np.arange(0, 40, 8))
    assert how == f"inputs: 'fold_8_kmeans_4_input' of {index_path}"
    inputs, _, how = eval_split(scene, 3, index=index, index_name=index_path)  # no 3-input entry: computed
    assert "k-means" in how
    np.testing.assert_array_equal(inputs, official_kmeans_split(scene.c2w[:, :3, 3], scene.c2w[:, :3, 2], 3)[0])
    with pytest.raises(
        ValueError,
        match=r"seq 'fold_8_kmeans_4_input' holds frame index 45, out of range for a scene "
        r"of 40 frames",
    ):
        eval_split(scene, 4, index={"seq": {"fold_8_kmeans_4_input": [1, 45, 2, 3]}}, index_name=index_path)
