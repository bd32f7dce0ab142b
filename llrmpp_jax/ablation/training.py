"""Training a row on procedural scenes: :func:`train` (data-parallel over the local
devices, the one objective :func:`row_objective` and the one stage loop
:func:`~llrmpp_jax.train.loop.run_stage`), :func:`init_model`."""

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
from llrmpp_jax.ablation.rows import Variant
from llrmpp_jax.ablation.scales import TRAIN_SCENES, Scale
from llrmpp_jax.data import BatchConfig, BatchIterator, ProceduralConfig, ProceduralSource
from llrmpp_jax.model import init_params
from llrmpp_jax.objective import LossWeights, make_objective
from llrmpp_jax.perceptual import load_vgg16_lpips
from llrmpp_jax.train.loop import StepInfo, run_stage

def row_objective(cfg: C.ModelConfig, scale: Scale, grad_weight: float, normal_weight: float, vgg: Any):
    """The training objective (:func:`llrmpp_jax.objective.objective`) of a row: colour loss
    with the scale's perceptual weight, plus the depth loss with the row's auxiliary weights
    when the model renders depth."""
    weights = LossWeights(perceptual=scale.perceptual_weight, depth_grad=grad_weight, depth_normal=normal_weight)
    return make_objective(cfg, weights, vgg)


def _device_count(batch: int) -> int:
    """Most local devices that split ``batch`` evenly."""
    return max(d for d in range(1, jax.local_device_count() + 1) if batch % d == 0)


def init_model(cfg: C.ModelConfig, scale: Scale, seed: int = 0) -> dict:
    """Fresh float32 parameters of ``cfg`` from ``seed``."""
    params = init_params(jax.random.key(seed), cfg, scale.num_inputs, scale.size, scale.size, scale.num_targets)
    # Parameters are float32 by contract (train state); cast leaves that x64 made float64.
    return jax.tree.map(lambda x: x if x.dtype == jnp.float32 else x.astype(jnp.float32), params)


@functools.lru_cache(maxsize=None)
def _train_fns(cfg: C.ModelConfig, scale: Scale, grad_weight: float, normal_weight: float):
    """``(optimizer, pmapped step)`` of a row, built once so its seeds share one compilation."""
    vgg = load_vgg16_lpips() if scale.perceptual_weight else None
    opt_cfg = T.OptimizerConfig(lr=scale.lr, warmup_steps=scale.warmup, total_steps=max(scale.steps, 1),
                                no_decay_names=("global_tokens",), spike_factor=scale.spike_factor)
    optimizer = T.make_optimizer(opt_cfg)
    step = T.pmap_train_step(T.make_train_step(
        row_objective(cfg, scale, grad_weight, normal_weight, vgg),
        optimizer, T.make_schedule(opt_cfg)), donate=True)
    init = jax.jit(lambda p, k: T.init_train_state(p, optimizer, k))
    return init, step


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


def train(cfg: C.ModelConfig, scale: Scale, variant: Variant, seed: int = 0, snapshots: Sequence[int] = ()
          ) -> Trained:
    """Train ``cfg`` for ``scale.steps`` steps on procedural scenes, data-parallel over the
    local devices (pmap step of :mod:`llrmpp_jax.train`). ``seed`` sets the init and the
    data order; every row sees the same batches for the same seed (paired comparisons).
    ``snapshots``: steps after which to keep a copy of the params (the pilot's budgets)."""
    t0 = time.perf_counter()
    depth = "depth" in cfg.outputs
    init, step = _train_fns(cfg, dataclasses.replace(scale, seeds=1), variant.grad_weight, variant.normal_weight)
    n_dev = _device_count(scale.batch)
    # One jitted init: optimizer.init run eagerly would compile a fill op per leaf shape.
    state = T.replicate_for_pmap(init(init_model(cfg, scale, seed), jax.random.key(seed)), n_dev)
    source = ProceduralSource(ProceduralConfig(height=scale.size, width=scale.size, num_frames=scale.frames),
                              size=TRAIN_SCENES)
    batch_cfg = BatchConfig(global_batch=scale.batch, num_inputs=scale.num_inputs, num_targets=scale.num_targets,
                            with_depth=depth, min_span=scale.min_span, max_span=scale.max_span, rescale=scale.rescale)
    losses, grad_norms, dropped, kept = [], [], [], {}
    host_params = lambda state: jax.tree.map(lambda x: x[0], jax.device_get(state.params))  # noqa: E731 (device 0's)

    def record(info: StepInfo) -> None:  # the loss curve, lost splat intersections, the snapshots asked for
        metrics = jax.device_get(info.metrics)  # host copies: indexing device arrays compiles ops
        losses.append(float(metrics["loss"][0]))
        grad_norms.append(float(metrics["grad_norm"][0]))
        dropped.append(float(metrics["splat_dropped"][0]) * n_dev)
        if info.step in snapshots:
            kept[info.step] = host_params(info.state)

    with BatchIterator(source, batch_cfg, seed=seed, num_devices=n_dev) as batches:
        done = run_stage(state, step, (T.shard_for_pmap(b, n_dev) for b in batches), steps=scale.steps,
                         hooks=[record])
    return Trained(host_params(done.state), np.asarray(losses, np.float32), np.asarray(grad_norms, np.float32),
                   time.perf_counter() - t0,
                   int(sum(dropped)), kept)
