"""The one training runner: a per-device train step as ``jax.jit`` over a device mesh.

``llrmpp train`` (:func:`llrmpp_jax.trainer.train`), every ablation row of the notebooks
(:func:`llrmpp_jax.ablation.training.train`) and the benchmarks train through a
:class:`Runner`: the step of :func:`~llrmpp_jax.train.step.make_train_step` under
:func:`~llrmpp_jax.train.step.sharded_train_step` (``shard_map`` over the mesh's
``"batch"`` axis), the state replicated and each batch split over that axis
(:mod:`llrmpp_jax.train.sharding`), the stage loop
:func:`~llrmpp_jax.train.loop.run_stage` with the caller's hooks. One host or many: the
mesh spans every global device by default, and each process feeds its own rows.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass
from typing import Any

from jax.sharding import Mesh

from llrmpp_jax.train.loop import Hook, StageRun, run_stage
from llrmpp_jax.train.sharding import host_copy, make_data_mesh, replicate_on_mesh, shard_for_mesh
from llrmpp_jax.train.state import TrainState
from llrmpp_jax.train.step import StepFn, sharded_train_step


@dataclass(frozen=True)
class Runner:
    """``step``: the jitted sharded step over ``mesh`` (``(state, batch) -> (state,
    metrics)``, state replicated, batch split over ``"batch"``, metrics replicated scalars).
    Built once per step function, so every run through it shares one compilation."""

    mesh: Mesh
    step: StepFn

    def place_state(self, state: TrainState) -> TrainState:
        """A host (or device) state as global arrays replicated over the mesh."""
        return replicate_on_mesh(host_copy(state), self.mesh)

    def place_batch(self, batch: Any) -> Any:
        """This process's rows ``[B_local, ...]`` of a batch as global arrays split over the mesh."""
        return shard_for_mesh(batch, self.mesh)

    def run(
        self,
        state: TrainState,
        batches: Iterable[Any],
        *,
        steps: int,
        start: int = 0,
        hooks: Sequence[Hook] = (),
        stop: Callable[[], bool] | None = None,
    ) -> StageRun:
        """Train ``state`` (host or device arrays) on the next host batch of ``batches`` from
        step ``start`` to ``steps`` (:func:`~llrmpp_jax.train.loop.run_stage`: hooks after each
        step, ``stop`` ends the stage early). The returned state is on the mesh:
        :func:`~llrmpp_jax.train.sharding.host_copy` brings it to the host."""
        return run_stage(
            self.place_state(state),
            self.step,
            map(self.place_batch, batches),
            steps=steps,
            start=start,
            hooks=hooks,
            stop=stop,
        )


def make_runner(step_fn: StepFn, mesh: Mesh | None = None, *, donate: bool = True) -> Runner:
    """The runner of the per-device ``step_fn`` over ``mesh`` (default: every global device,
    :func:`~llrmpp_jax.train.sharding.make_data_mesh`); ``donate`` reuses the state's
    buffers from step to step."""
    mesh = make_data_mesh() if mesh is None else mesh
    return Runner(mesh, sharded_train_step(step_fn, mesh, donate=donate))
