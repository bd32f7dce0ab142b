"""The data-parallel train step: ``(state, batch) -> (state, metrics)``, written per device.

The step sees its device's shard of the batch and averages the gradients, the loss and
the loss's metrics over the named axis ``"batch"`` with ``lax.pmean``. The runner
(:mod:`llrmpp_jax.train.runner`) runs it as ``jax.jit`` of a ``shard_map`` over a device
mesh (:func:`sharded_train_step`), on one host or many; the same function also runs under
``jax.pmap`` (:func:`pmap_train_step`, a compatibility wrapper the runner does not use).
With equal per-device shards the averaged gradient is the gradient of the global-batch
mean loss, so the update does not depend on the device count.

Long-LRM's guards (reference facts §2.1) are optax wrappers around the optimizer
(:func:`~llrmpp_jax.train.guards.guard_steps`): a step whose loss or gradient norm is not
finite is skipped -- zero updates, optimizer state bitwise unchanged, ``skipped``
incremented, ``step`` still advances (the data iterator and PRNG move on). With
``skip_grad_norm_above`` (Long-LRM: 5 x the clip norm 10 = 50) a finite step whose
pre-clip gradient norm exceeds it is skipped the same way, except that the learning-rate
schedule advances (Long-LRM still calls ``scheduler.step()`` there).
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import jax
import jax.numpy as jnp
import optax
from jax import lax
from jax.sharding import Mesh, NamedSharding, PartitionSpec

from llrmpp_jax.array_typing import Array, DTypeLike, Float, KeyArray
from llrmpp_jax.train.guards import guard_steps, skip_reasons
from llrmpp_jax.train.optimizer import schedule_count
from llrmpp_jax.train.state import TrainState, step_key

AXIS = "batch"
LossFn = Callable[[Any, Any, KeyArray], tuple[Float[Array, ""], dict[str, Array]]]
StepFn = Callable[[TrainState, Any], tuple[TrainState, dict[str, Array]]]
_RESERVED = ("loss", "grad_norm", "lr", "skipped", "skipped_total", "skipped_grad_norm", "skipped_grad_norm_total")


def _cast_floating(tree, dtype: DTypeLike):
    """Cast every floating leaf of ``tree`` to ``dtype`` (integer leaves untouched)."""
    return jax.tree.map(lambda x: x.astype(dtype) if jnp.issubdtype(x.dtype, jnp.floating) else x, tree)


def make_train_step(
    loss_fn: LossFn,
    optimizer: optax.GradientTransformation,
    schedule: optax.Schedule,
    *,
    compute_dtype: DTypeLike = jnp.float32,
    skip_grad_norm_above: float | None = None,
) -> StepFn:
    """Build the per-device train step (run by :func:`sharded_train_step`: shard_map over ``"batch"``).

    ``loss_fn(params, batch, key) -> (loss [], metrics {name: []})`` is the mean loss of
    this device's batch shard. With ``compute_dtype=jnp.bfloat16`` the float32 parameters
    are cast to bf16 before ``loss_fn`` (gradients, parameters and optimizer stay float32).
    ``schedule`` is the optimizer's learning-rate schedule; it is only reported.
    The step updates through ``guard_steps(optimizer, skip_grad_norm_above)``
    (:mod:`llrmpp_jax.train.guards`), whose state is ``optimizer``'s: non-finite steps
    are skipped, and with ``skip_grad_norm_above`` also steps whose finite (pre-clip)
    gradient norm exceeds it (Long-LRM's ``grad_clip_norm * allowed_gradnorm_factor`` =
    50): parameters and Adam moments stay unchanged (a zero update) but the schedule
    advances, as Long-LRM's scheduler does; ``None`` skips only non-finite steps, which
    leave the schedule where it was.

    The loss's key is ``fold_in(fold_in(base, step), device)``: deterministic per
    (step, device), so a random loss draws different noise on 1 and on 2 devices.

    Metrics (float32 ``[]``, identical on every device): ``loss``, ``grad_norm``, ``lr``
    (rate of this step's update), ``skipped`` (1.0 if this step was skipped, for either
    reason), ``skipped_total``, ``skipped_grad_norm`` (1.0 if skipped for its gradient
    norm), ``skipped_grad_norm_total`` (schedule count minus applied updates, so it counts
    only from a state whose schedule count started with it, as ``init_train_state``'s
    does), plus ``loss_fn``'s metrics averaged over devices.
    """
    compute_dtype = jnp.dtype(compute_dtype)
    if compute_dtype not in (jnp.dtype(jnp.float32), jnp.dtype(jnp.bfloat16)):
        raise ValueError(f"make_train_step: compute_dtype={compute_dtype}, expected float32 or bfloat16")

    def loss_and_metrics(params, batch, key):
        loss, metrics = loss_fn(_cast_floating(params, compute_dtype), batch, key)
        if jnp.shape(loss) != ():
            raise ValueError(f"loss_fn returned a loss of shape {jnp.shape(loss)}, expected a scalar ()")
        clash = sorted(set(metrics) & set(_RESERVED))
        if clash:
            raise ValueError(f"loss_fn metrics use reserved names {clash}; rename them")
        return loss.astype(jnp.float32), metrics

    guarded = guard_steps(optimizer, skip_grad_norm_above)

    def train_step(state: TrainState, batch: Any) -> tuple[TrainState, dict[str, Array]]:
        key = step_key(state, lax.axis_index(AXIS))
        # Mark the replicated parameters as device-varying so that, under shard_map's
        # varying-axes typing, their gradient stays per device (its transpose would
        # otherwise psum it) and the pmean below is the only reduction, as under pmap.
        params = lax.pcast(state.params, AXIS, to="varying")
        (loss, metrics), grads = jax.value_and_grad(loss_and_metrics, has_aux=True)(params, batch, key)
        grads = lax.pmean(grads, AXIS)
        loss = lax.pmean(loss, AXIS)
        metrics = lax.pmean(jax.tree.map(lambda x: jnp.asarray(x, jnp.float32), metrics), AXIS)
        grad_norm = optax.tree.norm(grads).astype(jnp.float32)
        nonfinite, too_large = skip_reasons(loss, grad_norm, skip_grad_norm_above)
        # optax mixes Python floats with its int32 count (``b1 ** count``), which strict
        # promotion rejects; its outputs keep the parameters' float32.
        with jax.numpy_dtype_promotion("standard"):
            updates, opt_state = guarded.update(grads, state.opt_state, state.params, loss=loss)
        params = optax.apply_updates(state.params, updates)
        skipped_now = (nonfinite | too_large).astype(jnp.int32)
        new_state = TrainState(
            step=state.step + 1,
            params=params,
            opt_state=opt_state,
            skipped=state.skipped + skipped_now,
            rng=state.rng,
        )
        count, new_count = schedule_count(state.opt_state), schedule_count(opt_state)
        if count is None:  # an optimizer without a schedule state: updates applied so far
            count = new_count = state.step - state.skipped
        applied = new_state.step - new_state.skipped
        metrics = dict(
            metrics,
            loss=loss,
            grad_norm=grad_norm,
            lr=jnp.asarray(schedule(count), jnp.float32),
            skipped=skipped_now.astype(jnp.float32),
            skipped_total=new_state.skipped.astype(jnp.float32),
            skipped_grad_norm=too_large.astype(jnp.float32),
            skipped_grad_norm_total=(new_count - applied).astype(jnp.float32),  # pyright: ignore[reportOptionalOperand] -- the optimizer state has a schedule count
        )
        return new_state, metrics

    return train_step


def state_sharding(mesh: Mesh) -> NamedSharding:
    """Where the runner keeps the train state on ``mesh``: replicated on every device."""
    return NamedSharding(mesh, PartitionSpec())


def batch_sharding(mesh: Mesh) -> NamedSharding:
    """Where the runner puts a global batch on ``mesh``: every leaf ``[B, ...]`` split along
    its leading axis over the mesh's ``"batch"`` axis (``B / n_dev`` rows a device)."""
    return NamedSharding(mesh, PartitionSpec(AXIS))


def sharded_train_step(step_fn: StepFn, mesh: Mesh, *, donate: bool = False) -> StepFn:
    """The runner's step: ``jax.jit`` of ``shard_map(step_fn)`` over ``mesh``'s ``"batch"``
    axis, ``(state, batch) -> (state, metrics)``. The state comes in and goes out on
    :func:`state_sharding` (replicated), the batch is a global ``[B, ...]`` array on
    :func:`batch_sharding`, the metrics are replicated float32 scalars. ``donate`` reuses
    the state's buffers.

    The shardings are fixed here, so ``sharded_train_step(step_fn, mesh).lower(state, batch)``
    also takes ``jax.ShapeDtypeStruct`` trees, for ahead-of-time compiles on any mesh
    (compile-only devices of another platform included). Multi-host: every process calls it
    with global arrays built from its process-local rows (``sharding.shard_for_mesh``)."""
    if AXIS not in mesh.axis_names:
        raise ValueError(f"sharded_train_step: mesh axes {mesh.axis_names} lack the data axis {AXIS!r}")
    mapped = jax.shard_map(
        step_fn,
        mesh=mesh,
        in_specs=(PartitionSpec(), PartitionSpec(AXIS)),
        out_specs=(PartitionSpec(), PartitionSpec()),
    )
    replicated, split = state_sharding(mesh), batch_sharding(mesh)
    return jax.jit(
        mapped,
        in_shardings=(replicated, split),
        out_shardings=(replicated, replicated),
        donate_argnums=(0,) if donate else (),
    )


def pmap_train_step(step_fn: StepFn, *, donate: bool = False) -> StepFn:
    """Compatibility wrapper, not used by the runner: ``step_fn`` under ``jax.pmap`` over
    the local devices, the one ``jax.pmap`` of the package. It shows the per-device step
    is still pmap-ready (``tests/train/test_step.py`` checks it against the runner).
    State replicated ``[n_dev, ...]``, batch ``[n_dev, B/n_dev, ...]``, metrics ``[n_dev]``
    (identical rows). ``donate`` reuses the state buffers."""
    return jax.pmap(step_fn, axis_name=AXIS, donate_argnums=(0,) if donate else ())
