"""``experiment_data``: the held-out samples an experiment asks for. Procedural scenes from
``eval_seed_offset``; views by ``procedural_eval`` ("split": the paper's every-8th split,
"window": one draw of the training view sampler seeded ``(seed, 7, i)``, or ``(7, i)``
when ``eval_views_follow_seed`` is False, as the ablations need); world units with
``rescale`` False. The oracle rebuilds each sample from the procedural scene and the
selection functions directly."""

import dataclasses

import numpy as np
import pytest

from llrmpp_jax import config as C
from llrmpp_jax.data import ProceduralConfig, ViewGeometry, eval_views, make_sample, procedural_scene, training_views
from llrmpp_jax.errors import UserError
from llrmpp_jax.experiment import DataConfig, ExperimentConfig, StageConfig
from llrmpp_jax.experiment_data import batch_config, eval_samples
from tests.helpers.typechecks import unchecked

PROC = ProceduralConfig(height=16, width=16, num_frames=17)


def experiment(seed: int = 3, **data) -> ExperimentConfig:
    stage = StageConfig(name="s", steps=1, global_batch=1, num_inputs=3, num_targets=2, resize_h=None)
    return ExperimentConfig(
        name="t",
        model=C.tiny(),
        stages=(stage,),
        seed=seed,
        data=DataConfig(procedural=PROC, eval_seed_offset=500, num_eval_scenes=2, **data),
    )


def expected(i: int, inputs, targets, rescale: bool = True) -> dict:
    return make_sample(procedural_scene(500 + i, PROC), inputs, targets, ViewGeometry(), rescale=rescale)


def assert_same(got: dict, want: dict) -> None:
    assert set(got) == set(want)
    for k in want:
        np.testing.assert_array_equal(got[k], want[k], err_msg=k)


@pytest.mark.parametrize("follow", [True, False])
def test_window_views_are_one_seeded_draw_of_the_training_sampler(follow):
    exp = experiment(eval_span=6, eval_views_follow_seed=follow)
    samples, names = eval_samples(exp, exp.stages[0])
    assert len(samples) == 2 and names == [procedural_scene(500 + i, PROC).name for i in range(2)]
    for i, s in enumerate(samples):
        rng = np.random.default_rng([3, 7, i] if follow else [7, i])
        inputs, targets = training_views(rng, PROC.num_frames, 3, 2, 6, 6, input_weight=0.0)
        assert inputs[-1] - inputs[0] == 6  # the window's span
        assert_same(s, expected(i, inputs, targets))
    other = experiment(seed=4, eval_span=6, eval_views_follow_seed=follow)
    moved = eval_samples(other, other.stages[0])[0]
    same = all(np.array_equal(a["target_c2w"], b["target_c2w"]) for a, b in zip(samples, moved))
    assert same == (not follow)  # another seed draws other views unless they are fixed


def test_split_views_in_world_units():
    exp = experiment(procedural_eval="split", rescale=False)
    samples, _ = eval_samples(exp, exp.stages[0])
    for i, s in enumerate(samples):
        inputs, targets = eval_views(procedural_scene(500 + i, PROC).c2w, 3)
        np.testing.assert_array_equal(targets, [0, 8, 16])
        assert_same(s, expected(i, inputs, targets, rescale=False))
        assert not np.allclose(s["input_c2w"], expected(i, inputs, targets)["input_c2w"])  # rescaling matters here


def test_rescale_reaches_the_training_batches_and_a_bad_view_rule_is_one_line():
    exp = experiment(rescale=False)
    assert batch_config(exp, exp.stages[0]).rescale is False
    assert batch_config(experiment(), exp.stages[0]).rescale is True
    with (
        pytest.raises(UserError, match="^DataConfig.procedural_eval must be 'window' or 'split', got 'every8'$"),
        unchecked(),
    ):
        dataclasses.replace(exp.data, procedural_eval="every8")
