"""Shipped weights (pretrained.py): checksum, config match, and one forward pass equal to the
one recorded when they were shipped."""

import json
import os
import shutil
from dataclasses import replace

import jax
import numpy as np
import pytest

from llrmpp_jax import config as C
from llrmpp_jax.experiment import load_experiment
from llrmpp_jax.model import flatten_params, init_params
from llrmpp_jax.params_io import load_params
from llrmpp_jax.pretrained import WEIGHTS_DIR, export_pretrained, load_pretrained, reference_forward
from tests.helpers.environment import ROOT

REFERENCE = {"seed": 5, "height": 64, "width": 64, "num_frames": 6, "inputs": [0, 4], "target": 2}


@pytest.fixture(scope="module")
def shipped_tmp(tmp_path_factory):
    """A random tiny model exported to a temporary weights folder."""
    cfg = C.tiny()
    params = init_params(jax.random.key(11), cfg, 2, 64, 64)
    d = str(tmp_path_factory.mktemp("weights"))
    meta = export_pretrained(params, cfg, "tiny", {"steps": 0}, REFERENCE, weights_dir=d)
    return d, cfg, params, meta


def test_export_then_load_gives_the_float16_params_and_the_recorded_forward(shipped_tmp):
    d, cfg, params, meta = shipped_tmp
    got, got_cfg = load_pretrained("tiny", cfg, weights_dir=d)
    assert got_cfg == cfg and meta["dtype"] == "float16" and meta["steps"] == 0
    want = flatten_params(params)
    for k, v in flatten_params(got).items():  # exactly the float16 rounding of what was exported
        assert v.dtype == np.float32  # pyright: ignore[reportAttributeAccessIssue] -- the npz holds arrays
        np.testing.assert_array_equal(v, np.asarray(want[k], np.float16).astype(np.float32), err_msg=k)
    recorded = np.load(os.path.join(d, "tiny.reference.npz"))["rgb"]
    assert recorded.shape == (64, 64, 3) and np.isfinite(recorded).all() and recorded.std() > 0
    np.testing.assert_allclose(reference_forward(got, got_cfg, meta["reference"]), recorded, rtol=0, atol=1e-6)


def test_wrong_checksum_is_one_line_naming_the_file(shipped_tmp, tmp_path):
    d, cfg, _, _ = shipped_tmp
    bad = str(tmp_path / "w")
    shutil.copytree(d, bad)
    path = os.path.join(bad, "tiny.npz")
    raw = bytearray(open(path, "rb").read())
    raw[len(raw) // 2] ^= 0x01  # one flipped bit inside the float16 data
    open(path, "wb").write(bytes(raw))
    with pytest.raises(
        ValueError, match=r"tiny\.npz: checksum mismatch: sha256 [0-9a-f]{16}\.\.\., tiny\.json records"
    ) as e:
        load_pretrained("tiny", cfg, weights_dir=bad)
    assert "\n" not in str(e.value)


def test_another_config_is_one_line_naming_the_field(shipped_tmp):
    d, cfg, _, _ = shipped_tmp
    other = replace(cfg, head=replace(cfg.head, feature_dim=8))
    with pytest.raises(
        ValueError,
        match=r"tiny\.npz: weights are for another model config: "
        r"model\.head\.feature_dim: shipped 16, expected 8$",
    ):
        load_pretrained("tiny", other, weights_dir=d)
    with pytest.raises(FileNotFoundError, match="no shipped model 'nope'"):
        load_pretrained("nope", weights_dir=d)


def test_a_field_added_after_shipping_takes_its_default(shipped_tmp, tmp_path):
    """A record written before a config field existed loads when the field's default is the
    expected value, and is refused, naming the field, when it is not."""
    d, cfg, _, _ = shipped_tmp
    old = str(tmp_path / "w")
    shutil.copytree(d, old)
    meta_path = os.path.join(old, "tiny.json")
    with open(meta_path) as f:
        meta = json.load(f)
    del meta["model"]["backbone"]["mamba"]["inter_chunk"]
    with open(meta_path, "w") as f:
        json.dump(meta, f)
    _, got_cfg = load_pretrained("tiny", cfg, weights_dir=old)
    assert got_cfg == cfg
    other = replace(cfg, backbone=replace(cfg.backbone, mamba=replace(cfg.backbone.mamba, inter_chunk="sequential")))
    with pytest.raises(
        ValueError, match=r"model\.backbone\.mamba\.inter_chunk: shipped 'auto', expected 'sequential'$"
    ):
        load_pretrained("tiny", other, weights_dir=old)


@pytest.mark.slow
def test_shipped_small_model_loads_and_reproduces_its_recorded_forward():
    """The model in the package: checksum, the config of the ``small`` recipe, provenance
    (the experiment it was fine-tuned with, ``small_accel_sharpen.py``, run twice: it also made
    the weights it started from; all of that model),
    and its recorded forward pass reproduced <= 1e-5 (float32 from the float16 file)."""
    exp = load_experiment("small")
    params, cfg = load_params("pretrained:small", exp.model)
    assert cfg == exp.model
    with open(os.path.join(WEIGHTS_DIR, "small.json")) as f:
        meta = json.load(f)
    start = meta["started_from"]
    assert (meta["experiment"], start["init"], start["experiment"]) == (
        "experiments/small_accel_sharpen.py",
        "pretrained:small",
        "experiments/small_accel_sharpen.py",
    )
    tuned = load_experiment(os.path.join(ROOT, meta["experiment"]))
    assert tuned.model == cfg
    assert meta["steps"] == start["steps"] + tuned.stages[0].steps
    assert len(meta["trained_at_commit"]) >= 7 and meta["held_out_scenes"] >= 16
    assert os.path.getsize(os.path.join(WEIGHTS_DIR, "small.npz")) <= 20e6
    recorded = np.load(os.path.join(WEIGHTS_DIR, "small.reference.npz"))["rgb"]
    np.testing.assert_allclose(reference_forward(params, cfg, meta["reference"]), recorded, rtol=0, atol=1e-5)
