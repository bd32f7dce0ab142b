"""Batch iterator: the documented layout, determinism in (seed, step) whatever the worker
count, resuming, per-process slices of the global batch, and skipping bad scenes."""

import warnings
from dataclasses import dataclass, replace

import jax
import numpy as np
import pytest

from llrmpp_jax.data.batching import BatchConfig, BatchIterator, FileSource, ProceduralSource, build_sample
from llrmpp_jax.data.preprocess import ViewGeometry
from llrmpp_jax.data.scene import Scene
from llrmpp_jax.data.synthetic import ProceduralConfig, procedural_scene
from llrmpp_jax.train.sharding import make_data_mesh, shard_for_mesh

SRC = ProceduralSource(ProceduralConfig(height=24, width=32, num_frames=10))
CFG = BatchConfig(global_batch=4, num_inputs=3, num_targets=2, geometry=ViewGeometry(multiple=8), with_depth=True)


def assert_batches_equal(a, b):
    assert a.keys() == b.keys()
    for k in a:
        np.testing.assert_array_equal(a[k], b[k])


def test_layout_and_values():
    with BatchIterator(SRC, CFG, seed=3, num_devices=2, num_workers=1) as it:
        b = next(it)
    shapes = {k: v.shape for k, v in b.items()}
    assert shapes == {
        "input_images": (4, 3, 24, 32, 3),
        "input_c2w": (4, 3, 4, 4),
        "input_intrinsics": (4, 3, 4),
        "target_images": (4, 2, 24, 32, 3),
        "target_c2w": (4, 2, 4, 4),
        "target_intrinsics": (4, 2, 4),
        "target_depth": (4, 2, 24, 32),
        "scene_scale": (4,),
    }
    assert all(v.dtype == np.float32 for v in b.values())
    assert b["input_images"].min() >= 0 and b["input_images"].max() <= 1
    np.testing.assert_allclose(np.abs(b["input_c2w"][..., :3, 3]).max(axis=(1, 2)), 1.0, rtol=1e-6)
    assert (b["target_depth"] > 0).all()
    mesh = make_data_mesh(jax.devices()[:2])
    sharded = shard_for_mesh(b, mesh)  # the runner's split of a batch over 2 devices
    assert sharded["target_depth"].shape == (4, 2, 24, 32)
    rows = {s.device: np.asarray(s.data) for s in sharded["input_c2w"].addressable_shards}
    np.testing.assert_array_equal(rows[mesh.devices[1]][0], b["input_c2w"][2])  # device 1 holds rows 2-3


def test_world_units_batch_is_the_rescaled_batch_undone():
    """``rescale=False``: same windows and images; poses and depths are the rescaled batch's
    divided by its per-sample scale (normalisation is a similarity), and against the
    procedural ray caster's own depth (the scene's world units) directly."""
    world_cfg = replace(CFG, rescale=False)
    with BatchIterator(SRC, CFG, seed=3, num_workers=1) as it:
        scaled = next(it)
    with BatchIterator(SRC, world_cfg, seed=3, num_workers=1) as it:
        world = next(it)
    assert not np.allclose(scaled["scene_scale"], 1.0)
    np.testing.assert_array_equal(world["scene_scale"], np.ones(4, np.float32))
    for k in ("input_images", "target_images", "input_intrinsics", "target_intrinsics"):
        np.testing.assert_array_equal(world[k], scaled[k])
    s = scaled["scene_scale"]
    np.testing.assert_allclose(world["target_depth"], scaled["target_depth"] / s[:, None, None, None], rtol=1e-5)
    for k in ("input_c2w", "target_c2w"):
        np.testing.assert_allclose(world[k][..., :3, :3], scaled[k][..., :3, :3], atol=1e-6)
        np.testing.assert_allclose(world[k][..., :3, 3], scaled[k][..., :3, 3] / s[:, None, None], rtol=1e-5, atol=1e-6)
    rng = np.random.default_rng([3, 0, 0, 0])  # element 0 of step 0 (test below)
    scene = SRC.load(int(rng.integers(len(SRC))))
    depths = np.stack([scene.depth(i) for i in range(len(scene))])
    assert any(np.allclose(world["target_depth"][0, 0], d, rtol=1e-5) for d in depths)


def test_batch_equals_its_elements_built_independently():
    """Element b of step s is build_sample with default_rng([seed, s, b, 0])."""
    with BatchIterator(SRC, CFG, seed=5, num_workers=1) as it:
        batch = it.batch_at(7)
    for b in range(4):
        ref = build_sample(SRC, CFG, np.random.default_rng([5, 7, b, 0]))
        for k in batch:
            np.testing.assert_array_equal(batch[k][b], ref[k])


def test_deterministic_resumable_and_worker_independent():
    with BatchIterator(SRC, CFG, seed=11, num_workers=2, prefetch=3) as it:
        first = [next(it) for _ in range(4)]
        assert it.state() == {"seed": 11, "step": 4}
    with BatchIterator(SRC, CFG, seed=11, start_step=2, num_workers=1, prefetch=1) as it:
        resumed = [next(it) for _ in range(2)]
    for a, b in zip(first[2:], resumed):
        assert_batches_equal(a, b)
    assert not np.array_equal(first[0]["input_images"], first[1]["input_images"])
    with BatchIterator(SRC, CFG, seed=12, num_workers=1) as it:
        assert not np.array_equal(next(it)["input_images"], first[0]["input_images"])


def test_process_slices_tile_the_global_batch():
    with BatchIterator(SRC, CFG, seed=2, num_workers=1) as it:
        whole = it.batch_at(1)
    parts = []
    for pid in range(2):
        with BatchIterator(SRC, CFG, seed=2, process_index=pid, process_count=2, num_workers=1) as it:
            parts.append(it.batch_at(1))
    for k in whole:
        np.testing.assert_array_equal(np.concatenate([p[k] for p in parts]), whole[k])
    with pytest.raises(ValueError, match="does not split over 3 devices"):
        BatchIterator(SRC, CFG, seed=0, num_devices=3)


@dataclass
class FlakySource:
    """Scenes 0 and 2 are broken in different ways; 1 and 3 are fine."""

    def __len__(self):
        return 4

    def load(self, index: int) -> Scene:
        if index == 0:
            raise FileNotFoundError("image file not found: /data/scene0/images/00003.png")
        if index == 2:
            return procedural_scene(2, ProceduralConfig(height=24, width=32, num_frames=2))  # too few frames
        return procedural_scene(index, ProceduralConfig(height=24, width=32, num_frames=10))


def test_bad_scenes_are_skipped_counted_and_warned():
    src = FlakySource()
    it = BatchIterator(src, CFG, seed=0, num_workers=1)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        batches = [it.batch_at(step) for step in range(3)]
    it.close()
    msgs = [str(w.message) for w in caught]
    assert it.skipped == len(msgs) > 0
    assert any("00003.png" in m for m in msgs) and any("fewer than the 3 views" in m for m in msgs)
    # oracle: each element is the first attempt whose scene builds
    for step, batch in enumerate(batches):
        for b in range(4):
            for attempt in range(CFG.max_attempts):
                rng = np.random.default_rng([0, step, b, attempt])
                if int(np.random.default_rng([0, step, b, attempt]).integers(len(src))) in (1, 3):
                    ref = build_sample(src, CFG, rng)
                    break
            np.testing.assert_array_equal(batch["input_images"][b], ref["input_images"])


def test_all_scenes_bad_raises():
    def broken(path):
        raise ValueError(f"{path}: corrupt")

    cfg = BatchConfig(global_batch=1, num_inputs=2, num_targets=1, max_attempts=3)
    with BatchIterator(FileSource(["a.json", "b.json"], broken), cfg, seed=0, num_workers=1) as it:
        with pytest.raises(RuntimeError, match="3 scenes in a row failed"), warnings.catch_warnings():
            warnings.simplefilter("ignore")
            next(it)


@pytest.mark.parametrize("reverse,shuffle", [(1.0, 0.0), (0.0, 1.0), (1.0, 1.0)])
def test_input_order_augmentations_permute_views_whole(reverse, shuffle):
    """Reversed / shuffled inputs are a permutation of the sorted draw that moves image,
    camera and intrinsics together: each augmented view equals the plain view with the same
    camera centre (the normalisation uses means and a max, so it is order-free up to
    rounding); targets are untouched. Reverse alone is exactly the reversal."""
    src = ProceduralSource(ProceduralConfig(height=24, width=32, num_frames=16))
    plain = BatchConfig(global_batch=1, num_inputs=6, num_targets=2)
    aug = BatchConfig(global_batch=1, num_inputs=6, num_targets=2, reverse_prob=reverse, shuffle_prob=shuffle)
    for seed in range(3):
        a = build_sample(src, plain, np.random.default_rng([1, seed]))
        b = build_sample(src, aug, np.random.default_rng([1, seed]))
        d = np.linalg.norm(b["input_c2w"][:, None, :3, 3] - a["input_c2w"][None, :, :3, 3], axis=-1)
        perm = np.argmin(d, axis=1)
        assert sorted(perm.tolist()) == list(range(6)) and d[np.arange(6), perm].max() < 1e-5
        np.testing.assert_array_equal(b["input_images"], a["input_images"][perm])
        np.testing.assert_array_equal(b["input_intrinsics"], a["input_intrinsics"][perm])
        np.testing.assert_allclose(b["input_c2w"], a["input_c2w"][perm], atol=1e-5)
        np.testing.assert_array_equal(b["target_images"], a["target_images"])
        if shuffle == 0.0:
            np.testing.assert_array_equal(perm, np.arange(6)[::-1])
        else:
            assert not np.array_equal(perm, np.arange(6))


def test_worker_processes_give_the_threads_batches_and_report_skips():
    """Elements built in spawned processes: the same batches as in-thread building (step by
    step, resumed), and the bad scenes they pass over counted and warned in this process."""
    with BatchIterator(SRC, CFG, seed=4, num_workers=1) as it:
        want = [next(it) for _ in range(3)]
    with BatchIterator(SRC, CFG, seed=4, num_workers=2, worker_processes=True) as it:
        got = [next(it) for _ in range(3)]
        assert it.state() == {"seed": 4, "step": 3}
    for a, b in zip(got, want):
        assert_batches_equal(a, b)
    src = FlakySource()
    with BatchIterator(src, CFG, seed=0, num_workers=1) as it, warnings.catch_warnings(record=True) as w_threads:
        warnings.simplefilter("always")
        want = it.batch_at(1)
    with (
        BatchIterator(src, CFG, seed=0, num_workers=2, worker_processes=True) as it,
        warnings.catch_warnings(record=True) as w_procs,
    ):
        warnings.simplefilter("always")
        got = it.batch_at(1)
        assert it.skipped == len(w_procs) == len(w_threads) > 0
    assert [str(w.message) for w in w_procs] == [str(w.message) for w in w_threads]
    assert_batches_equal(got, want)
