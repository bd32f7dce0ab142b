"""Model-agnostic training machinery: optimizer, train state, data-parallel step,
device placement and verified orbax checkpoints."""

from llrmpp_jax.train.checkpoint import (
    CorruptCheckpointError,
    IncompatibleCheckpointError,
    Restored,
    recorded_config,
    restore_checkpoint,
    save_checkpoint,
    verify_checkpoint,
)
from llrmpp_jax.train.interrupt import StopRequest, stop_on_signals
from llrmpp_jax.train.optimizer import (
    LONG_LRM_TRAIN_STEPS,
    OptimizerConfig,
    make_optimizer,
    make_schedule,
    warmup_cosine_schedule,
    weight_decay_mask,
)
from llrmpp_jax.train.sharding import (
    make_data_mesh,
    replicate_for_pmap,
    replicate_on_mesh,
    shard_for_mesh,
    shard_for_pmap,
    unreplicate,
)
from llrmpp_jax.train.state import TrainState, init_train_state, step_key
from llrmpp_jax.train.step import (
    AXIS,
    make_train_step,
    pmap_train_step,
    sharded_train_step,
)

__all__ = [
    "AXIS",
    "CorruptCheckpointError",
    "IncompatibleCheckpointError",
    "LONG_LRM_TRAIN_STEPS",
    "OptimizerConfig",
    "Restored",
    "recorded_config",
    "StopRequest",
    "TrainState",
    "init_train_state",
    "make_data_mesh",
    "make_optimizer",
    "make_schedule",
    "make_train_step",
    "pmap_train_step",
    "replicate_for_pmap",
    "replicate_on_mesh",
    "restore_checkpoint",
    "save_checkpoint",
    "shard_for_mesh",
    "shard_for_pmap",
    "sharded_train_step",
    "step_key",
    "stop_on_signals",
    "unreplicate",
    "verify_checkpoint",
    "warmup_cosine_schedule",
    "weight_decay_mask",
]
