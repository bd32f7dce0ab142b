"""What a training stage's batches look like: view geometry (resize, crop, zoom), view
counts and spans, and whether they carry target depth, from an experiment and its stage."""

from __future__ import annotations

from typing import TYPE_CHECKING

from llrmpp_jax.data.batching import BatchConfig
from llrmpp_jax.data.preprocess import ViewGeometry

if TYPE_CHECKING:  # experiment imports data (ProceduralConfig): no runtime import back
    from llrmpp_jax.experiment import ExperimentConfig, StageConfig


def view_geometry(stage: StageConfig, multiple: int, train: bool = True) -> ViewGeometry:
    """``stage``'s image geometry, sides rounded to ``multiple``; ``train`` False (held-out
    views): no random zoom."""
    return ViewGeometry(resize_h=stage.resize_h, resize_w=stage.resize_w, multiple=multiple,
                        square_crop=stage.square_crop, zoom_min=stage.zoom_min if train else 1.0)


def needs_depth(exp: ExperimentConfig) -> bool:
    """Whether batches carry ground-truth target depth (a depth output or the Gaussian depth term)."""
    return "depth" in exp.model.outputs or exp.gaussian_depth_weight > 0


def batch_config(exp: ExperimentConfig, stage: StageConfig) -> BatchConfig:
    """The training batches of ``stage`` of ``exp``."""
    return BatchConfig(
        global_batch=stage.global_batch, num_inputs=stage.num_inputs, num_targets=stage.num_targets,
        geometry=view_geometry(stage, exp.model.size_multiple), min_span=stage.min_span,
        max_span=stage.max_span, input_weight=stage.input_weight,
        reverse_prob=stage.reverse_prob, shuffle_prob=stage.shuffle_prob,
        with_depth=needs_depth(exp),
    )
