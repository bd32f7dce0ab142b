"""The smallest experiment that trains: the tiny model on 32 x 32 procedural scenes, a
single stage of a few steps (checkpoint every step, evaluation every 2), no perceptual loss.
Experiment files written by the tests import it from here (``sys.path`` holds the checkout)."""

from dataclasses import replace

from llrmpp_jax import config as C
from llrmpp_jax.data import ProceduralConfig
from llrmpp_jax.experiment import DataConfig, ExperimentConfig, StageConfig


def micro_experiment(steps: int = 2) -> ExperimentConfig:
    model = replace(
        C.tiny(), head=C.GaussianHeadConfig(gaussians_per_token=2, feature_dim=8, max_dist=8.0, scale_bias=-2.5)
    )
    return ExperimentConfig(
        name="micro",
        model=model,
        stages=(
            StageConfig(
                "s1",
                steps=steps,
                global_batch=2,
                num_inputs=2,
                num_targets=1,
                resize_h=32,
                square_crop=True,
                lr=1e-3,
                warmup_steps=1,
            ),
        ),
        data=DataConfig(procedural=ProceduralConfig(height=32, width=32, num_frames=6), num_eval_scenes=1, workers=1),
        perceptual_weight=0.0,
        log_every=1,
        eval_every=2,
        checkpoint_every=1,
    )
