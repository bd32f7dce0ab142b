"""The one runner: ``llrmpp train``'s path (``trainer.train``) and a notebook ablation row's
path (``ablation.training.train``) train the same experiment to the same losses, step for
step, and the same parameters (same config, seed and batches; both through
``train.runner``). Exact equality: the two compile the same program from the same inputs,
so any difference in objective, optimizer, initial state, batches or device layout shows."""

import dataclasses

import jax
import numpy as np
import pytest

from llrmpp_jax import ablation
from llrmpp_jax.ablation.rows import Variant
from llrmpp_jax.ablation.training import row_experiment
from llrmpp_jax.trainer import train
from tests.helpers.toy_train import assert_tree_equal


@pytest.mark.slow
def test_llrmpp_train_and_an_ablation_row_give_the_same_losses(tmp_path):
    assert jax.device_count() == 2  # both paths split the batch of 2 over the 2 devices
    scale = ablation.make_scale("smoke", paper_views=2, depth=True)
    # The spike guard is the one row setting an experiment cannot hold: off for the comparison.
    scale = dataclasses.replace(scale, steps=4, warmup=2, spike_factor=None)
    variant = Variant(labels={}, build=None, paper={}, grad_weight=0.2, normal_weight=0.05)
    seed = 3
    row = ablation.train(scale.base, scale, variant, seed=seed)
    exp = row_experiment(scale.base, scale, seed, variant.grad_weight, variant.normal_weight)
    result = train(exp, str(tmp_path / "work"), progress=False)

    losses = np.asarray([h["loss"] for h in result["history"]], np.float32)
    assert [h["step"] for h in result["history"]] == [1, 2, 3, 4]
    assert np.all(np.isfinite(row.losses)) and len(set(row.losses.tolist())) == 4  # a real, moving curve
    np.testing.assert_array_equal(losses, row.losses)
    np.testing.assert_array_equal(np.asarray([h["grad_norm"] for h in result["history"]], np.float32), row.grad_norms)
    assert_tree_equal(result["params"], row.params)
