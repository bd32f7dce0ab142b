"""Model-agnostic training machinery: optimizer and its guards, train state, data-parallel
step, the one runner (jit over a device mesh), device placement and verified orbax
checkpoints."""

from llrmpp_jax.train.checkpoint import (
    CorruptCheckpointError,
    IncompatibleCheckpointError,
    Restored,
    recorded_config,
    restore_checkpoint,
    save_checkpoint,
    verify_checkpoint,
)
from llrmpp_jax.train.guards import guard_steps, skip_large_gradients, skip_nonfinite, skip_reasons
from llrmpp_jax.train.interrupt import StopRequest, stop_on_signals
from llrmpp_jax.train.optimizer import (
    LONG_LRM_TRAIN_STEPS,
    OptimizerConfig,
    make_optimizer,
    make_schedule,
    warmup_cosine_schedule,
    weight_decay_mask,
)
from llrmpp_jax.train.runner import Runner, make_runner
from llrmpp_jax.train.sharding import (
    host_copy,
    make_data_mesh,
    replicate_on_mesh,
    shard_for_mesh,
)
from llrmpp_jax.train.state import TrainState, init_train_state, step_key
from llrmpp_jax.train.step import (
    AXIS,
    batch_sharding,
    make_train_step,
    sharded_train_step,
    state_sharding,
)

__all__ = [
    "AXIS",
    "CorruptCheckpointError",
    "IncompatibleCheckpointError",
    "LONG_LRM_TRAIN_STEPS",
    "OptimizerConfig",
    "Restored",
    "Runner",
    "StopRequest",
    "TrainState",
    "batch_sharding",
    "guard_steps",
    "host_copy",
    "init_train_state",
    "make_data_mesh",
    "make_optimizer",
    "make_runner",
    "make_schedule",
    "make_train_step",
    "recorded_config",
    "replicate_on_mesh",
    "restore_checkpoint",
    "save_checkpoint",
    "shard_for_mesh",
    "sharded_train_step",
    "skip_large_gradients",
    "skip_nonfinite",
    "skip_reasons",
    "state_sharding",
    "step_key",
    "stop_on_signals",
    "verify_checkpoint",
    "warmup_cosine_schedule",
    "weight_decay_mask",
]
