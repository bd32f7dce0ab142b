"""Where scenes come from: a dataset's held-out split (``DataConfig.eval_split``) on a fake
ScanNet export laid out by split, its scene list and the one-line errors for a bad split
name or a listed room that is not on disk; training on the evaluated split leaves out only
the evaluated rooms' target frames."""

import dataclasses
import os

import numpy as np
import pytest

from llrmpp_jax.data.formats import read_scannet_scene
from llrmpp_jax.errors import MissingInputError, UserError
from llrmpp_jax.experiment import DataConfig, load_experiment
from llrmpp_jax.experiment_data import held_out_description, scene_source
from tests.helpers.fake_scannet import FRAMES, ROOMS, fake_scannet, split_data
from tests.helpers.typechecks import unchecked


@pytest.fixture(scope="module")
def scannet_root(tmp_path_factory):
    return fake_scannet(tmp_path_factory.mktemp("scannet"))


def test_the_scannet_recipe_evaluates_the_test_split():
    data = load_experiment("scannet").data
    assert data.eval_split == "test" and data.num_eval_scenes == 100
    assert data.held_out_path == "data/scannet/test"
    assert data.held_out_list == "data/scannet/scannetv2_test.txt"
    assert data.path == "data/scannet/train" and not data.eval_reads_training_scenes


def test_a_split_reads_the_rooms_its_list_names_in_its_order(scannet_root):
    test = scene_source(split_data(scannet_root, "test"), held_out=True)
    assert [os.path.basename(p) for p in test.paths] == ["scene0708_00", "scene0707_00"]  # scene0709_00: not listed  # pyright: ignore[reportAttributeAccessIssue] -- the source made here is a FileSource (a HeldOutSource for .base), which has it
    assert test.load(0).name == "scene0708_00" and len(test.load(0)) == FRAMES
    val = scene_source(split_data(scannet_root, "val"), held_out=True)
    assert val.paths == [os.path.join(scannet_root, "val", "scene0011_00")]  # pyright: ignore[reportAttributeAccessIssue] -- the source made here is a FileSource (a HeldOutSource for .base), which has it
    assert held_out_description(split_data(scannet_root, "val")) == (
        f"split val: the first 100 scenes named in {scannet_root}/scannetv2_val.txt in {scannet_root}/val"
    )
    # without a list: every room of the split's folder, sorted
    unlisted = scene_source(split_data(scannet_root, "test", scene_list=None), held_out=True)
    assert [os.path.basename(p) for p in unlisted.paths] == ROOMS["test"]  # pyright: ignore[reportAttributeAccessIssue] -- the source made here is a FileSource (a HeldOutSource for .base), which has it


def test_bad_splits_and_lists_are_one_line(tmp_path, scannet_root):
    with pytest.raises(UserError, match=r"^the split must be 'train', 'val' or 'test', got 'dev'$"), unchecked():
        split_data(scannet_root, "dev")
    with pytest.raises(UserError, match=r"names a \{split\} but eval_split is None"):
        split_data(scannet_root, None)  # pyright: ignore[reportArgumentType] -- None on purpose: the test wants its error
    with pytest.raises(UserError, match=r"eval_split='test' selects nothing: name it as \{split\}"):
        DataConfig(kind="scannet", path=scannet_root, eval_path=scannet_root, eval_split="test")
    lists = tmp_path / "lists"
    lists.mkdir()
    (lists / "scannetv2_test.txt").write_text("scene0707_00\nscene0710_00\n\nscene0711_00\n")
    (lists / "scannetv2_val.txt").write_text("\n")
    data = split_data(scannet_root, "test", scene_list=str(lists / "scannetv2_{split}.txt"))
    with pytest.raises(MissingInputError) as err:
        scene_source(data, held_out=True)
    assert str(err.value) == (
        f"scene list {lists}/scannetv2_test.txt: 2 of its 3 scenes are not folders of "
        f"{scannet_root}/test, the first: scene0710_00"
    )
    with pytest.raises(UserError, match=r"scannetv2_val.txt names no scenes$"):
        scene_source(dataclasses.replace(data, eval_split="val"), held_out=True)
    with pytest.raises(MissingInputError, match=r"^scene list not found: .*/scannetv2_train.txt$"):
        scene_source(dataclasses.replace(data, eval_split="train"), held_out=True)


def test_training_on_the_evaluated_split_leaves_out_only_its_evaluated_rooms_targets(tmp_path):
    """Evaluating the train split (its list names only scene0001_00) while training on it:
    scene0001_00 loses the evaluation's targets (frames 0 and 8), scene0000_00 keeps all."""
    root = fake_scannet(tmp_path, size=8, lists={"train": ["scene0001_00"]})
    data = split_data(root, "train")
    assert data.eval_reads_training_scenes
    training = scene_source(data)
    full = read_scannet_scene(os.path.join(root, "train", "scene0001_00"))
    kept = {os.path.basename(training.base.paths[i]): training.load(i) for i in range(len(training))}  # pyright: ignore[reportAttributeAccessIssue] -- the source made here is a FileSource (a HeldOutSource for .base), which has it
    assert len(kept["scene0000_00"]) == FRAMES and len(kept["scene0001_00"]) == FRAMES - 2
    np.testing.assert_array_equal(kept["scene0001_00"].c2w, np.delete(full.c2w, [0, 8], axis=0))
