"""The programs a plan compiles, built from shapes alone for a mesh of (compile-only) devices.

Each :class:`Program` returns, for a :class:`jax.sharding.Mesh` with a ``"batch"`` axis, a
jitted function and its arguments as ``jax.ShapeDtypeStruct`` s carrying their shardings:
parameters and optimizer state replicated, images and cameras split over ``"batch"``.
Nothing is allocated, so paper-size programs are planned on a laptop. The model is the
recipe's, with :func:`llrmpp_jax.config.for_accelerators` for the target's backend (on TPU
the Pallas splash attention kernel and the sequential SSD recurrence), parameters in bf16 where
the recipe computes in bf16, as the trainer's step casts them.

Programs (per device, one scene each unless the recipe's stage says otherwise):

* ``reconstruct_<V>``: images + cameras of one scene of V inputs at 544x960 -> Gaussians
  (Table 1 of the paper: 16, 32 and 64 inputs).
* ``render``: one 544x960 target from the Gaussians of 32 inputs (the S partition copies
  splatted, then the decoder).
* ``train_<recipe>_<stage>``: the trainer's step of that stage (loss, gradient, pmean over
  ``"batch"``, AdamW update, guards), donated state, with the stage's inputs and targets at its
  size (the side rounded up to the model's size multiple; 540-high stages at 16:9, 544x960),
  the recipe's global batch over the paper's 64 GPUs per device (stage 1 of ``dl3dv``: 4
  scenes). The perceptual network's weights are an argument (random, of VGG19's shapes: a
  step's memory and time depend on shapes only).
* ``tiny_reconstruct``, ``tiny_render``, ``tiny_train``: the same three on
  :func:`llrmpp_jax.config.tiny` at 2 + 1 views of 64x96: the suite's compile guard.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, replace

import jax
import jax.numpy as jnp
import numpy as np
from jax.sharding import Mesh, NamedSharding, PartitionSpec

from llrmpp_jax import config as C
from llrmpp_jax.errors import UserError
from llrmpp_jax.plan.catalog import GROUPS, PROGRAM_NAMES

AXIS = "batch"
PAPER_DEVICES = 64  # paper Table 8: the global batch of every stage trains on 64 GPUs
PAPER_SIZE = (544, 960)  # 960x540 rounded up to the model's size multiple
Built = tuple[Callable, tuple]


@dataclass(frozen=True)
class Program:
    """A named program: ``build(mesh, backend)`` -> (jitted fn, abstract args); ``flops(backend)``
    -> model FLOPs per device (matrix products of the computation, no recomputation: the
    tensor-core work a chip must do), or None; ``describe`` in one line."""

    name: str
    describe: str
    build: Callable[[Mesh, str], Built]
    flops: Callable[[str], float] | None = None


def _abstract(tree, sharding: NamedSharding):
    return jax.tree.map(lambda x: jax.ShapeDtypeStruct(np.shape(x), x.dtype, sharding=sharding), tree)


def _params_shapes(cfg: C.ModelConfig, bf16: bool):
    from llrmpp_jax.model import init_params

    shapes = jax.eval_shape(lambda k: init_params(k, C.with_attention(cfg, "xla"), 2, 32, 32), jax.random.key(0))
    dtype = jnp.bfloat16 if bf16 else jnp.float32
    return jax.tree.map(
        lambda s: jax.ShapeDtypeStruct(s.shape, dtype if jnp.issubdtype(s.dtype, jnp.floating) else s.dtype), shapes
    )


def _views(b: int, v: int, h: int, w: int, role: str) -> dict:
    return {
        f"{role}_images": jax.ShapeDtypeStruct((b, v, h, w, 3), jnp.float32),
        f"{role}_c2w": jax.ShapeDtypeStruct((b, v, 4, 4), jnp.float32),
        f"{role}_intrinsics": jax.ShapeDtypeStruct((b, v, 4), jnp.float32),
    }


def _round_up(x: int, m: int) -> int:
    return int(math.ceil(x / m) * m)


def _model(cfg: C.ModelConfig, backend: str) -> C.ModelConfig:
    return C.for_accelerators(cfg, backend=backend)


def reconstruct_program(
    cfg: C.ModelConfig, views: int, size: tuple[int, int], bf16: bool, name: str | None = None
) -> Program:
    """``reconstruct`` of ``views`` inputs of ``size`` (h, w), one scene per device (``name``:
    ``reconstruct_<views>`` by default)."""
    from llrmpp_jax.benchmarks.measure import matmul_flops
    from llrmpp_jax.benchmarks.paper import counting_config
    from llrmpp_jax.model import reconstruct

    h, w = size

    def args(mesh: Mesh | None, n: int):
        rep = NamedSharding(mesh, PartitionSpec()) if mesh else None
        split = NamedSharding(mesh, PartitionSpec(AXIS)) if mesh else None
        inputs = _views(n, views, h, w, "input")
        params = _params_shapes(cfg, bf16)
        return (
            params if rep is None else _abstract(params, rep),
            *(x if split is None else _abstract(x, split) for x in inputs.values()),
        )

    def build(mesh: Mesh, backend: str) -> Built:
        model = _model(cfg, backend)
        fn = jax.jit(lambda p, i, c, k: reconstruct(p, model, i, c, k))
        return fn, args(mesh, mesh.size)

    def flops(backend: str) -> float:
        count = counting_config(_model(cfg, backend))
        return matmul_flops(lambda p, i, c, k: reconstruct(p, count, i, c, k), *args(None, 1))

    return Program(name or f"reconstruct_{views}", f"reconstruct {views} inputs of {h}x{w} (one scene)", build, flops)


def render_program(
    cfg: C.ModelConfig, from_views: int, size: tuple[int, int], bf16: bool, name: str = "render"
) -> Program:
    """``render`` of one ``size`` target from the Gaussians of ``from_views`` inputs."""
    from llrmpp_jax.benchmarks.measure import matmul_flops
    from llrmpp_jax.benchmarks.paper import counting_config
    from llrmpp_jax.model import reconstruct, render

    h, w = size

    def args(model: C.ModelConfig, mesh: Mesh | None, n: int):
        params = _params_shapes(cfg, bf16)
        inputs = _views(n, from_views, h, w, "input")
        gaussians = jax.eval_shape(lambda p, i, c, k: reconstruct(p, model, i, c, k), params, *inputs.values())
        target = _views(n, 1, h, w, "target")
        out = (params, gaussians, target["target_c2w"], target["target_intrinsics"])
        if mesh is None:
            return out
        rep, split = NamedSharding(mesh, PartitionSpec()), NamedSharding(mesh, PartitionSpec(AXIS))
        return (_abstract(out[0], rep), *(_abstract(x, split) for x in out[1:]))

    def build(mesh: Mesh, backend: str) -> Built:
        model = _model(cfg, backend)
        fn = jax.jit(lambda p, g, c, k: render(p, model, g, c, k, h, w).images)
        return fn, args(model, mesh, mesh.size)

    def flops(backend: str) -> float:
        count = counting_config(_model(cfg, backend))
        return matmul_flops(lambda p, g, c, k: render(p, count, g, c, k, h, w).images, *args(count, None, 1))

    return Program(name, f"render one {h}x{w} target from {from_views} inputs' Gaussians", build, flops)


def stage_size(cfg: C.ModelConfig, stage) -> tuple[int, int]:
    """A stage's (h, w) as a plan compiles it: the stage's resize, 540-high stages at 16:9
    (DL3DV's 960x540), square crops square, each side rounded up to the model's size multiple."""
    h = stage.resize_h
    w = stage.resize_w or (h if stage.square_crop else round(h * 16 / 9))
    m = cfg.size_multiple
    return _round_up(h, m), _round_up(w, m)


def train_program(
    exp,
    stage,
    name: str,
    views: tuple[int, int] | None = None,
    size: tuple[int, int] | None = None,
    per_device_batch: int | None = None,
) -> Program:
    """The trainer's step of ``stage`` of experiment ``exp`` (``views`` = (inputs, targets),
    ``size`` and ``per_device_batch`` override the stage's)."""
    from llrmpp_jax import train as T
    from llrmpp_jax.benchmarks.paper import train_step_model_flops
    from llrmpp_jax.benchmarks.paper_step import perceptual_for_compile
    from llrmpp_jax.model import init_params
    from llrmpp_jax.objective import make_loss_fn
    from llrmpp_jax.trainer import optimizer_config

    v, t = views or (stage.num_inputs, stage.num_targets)
    h, w = size or stage_size(exp.model, stage)
    b = per_device_batch or max(1, stage.global_batch // PAPER_DEVICES)
    opt_cfg = optimizer_config(stage)
    vgg = perceptual_for_compile(exp)
    vgg_shapes = None if vgg is None else jax.tree.map(lambda x: jax.ShapeDtypeStruct(x.shape, x.dtype), vgg)

    def batch(n: int) -> dict:
        return {**_views(n, v, h, w, "input"), **_views(n, t, h, w, "target")}

    def build(mesh: Mesh, backend: str) -> Built:
        e = replace(exp, model=_model(exp.model, backend))
        optimizer = T.make_optimizer(opt_cfg)
        params = jax.eval_shape(
            lambda k: init_params(k, C.with_attention(e.model, "xla"), 2, 32, 32), jax.random.key(0)
        )
        state = jax.eval_shape(lambda p: T.init_train_state(p, optimizer, jax.random.key(1)), params)

        def per_device(state, batch, vgg_params):
            # The step is built inside the trace so that the perceptual weights are an
            # argument rather than constants folded into the program.
            step = T.make_train_step(
                make_loss_fn(e, vgg_params, stage),
                optimizer,
                T.make_schedule(opt_cfg),
                compute_dtype=jnp.bfloat16 if e.bf16 else jnp.float32,
                skip_grad_norm_above=e.skip_grad_norm_above,
            )
            return step(state, batch)

        rep, split = PartitionSpec(), PartitionSpec(AXIS)
        mapped = jax.shard_map(per_device, mesh=mesh, in_specs=(rep, split, rep), out_specs=(rep, rep))
        fn = jax.jit(mapped, donate_argnums=(0,))
        r, s = NamedSharding(mesh, rep), NamedSharding(mesh, split)
        return fn, (
            _abstract(state, r),
            _abstract(batch(b * mesh.size), s),
            None if vgg_shapes is None else _abstract(vgg_shapes, r),
        )

    def flops(backend: str) -> float:
        e = replace(exp, model=_model(exp.model, backend))
        return train_step_model_flops(e, vgg_shapes, batch(b))

    return Program(
        name, f"train step of {exp.name}/{stage.name}: {b} x ({v} inputs + {t} targets) at {h}x{w}", build, flops
    )


def _paper_programs() -> dict[str, Callable[[], Program]]:
    from llrmpp_jax.experiment import load_experiment

    out: dict[str, Callable[[], Program]] = {}
    for v in (16, 32, 64):
        out[f"reconstruct_{v}"] = lambda v=v: reconstruct_program(C.paper_dl3dv(), v, PAPER_SIZE, True)
    out["render"] = lambda: render_program(C.paper_dl3dv(), 32, PAPER_SIZE, True)
    for recipe, n in (("dl3dv", 4), ("scannet", 3)):
        for i in range(n):

            def make(recipe=recipe, i=i) -> Program:
                exp = load_experiment(recipe)
                stage = exp.stages[i]
                return train_program(exp, stage, f"train_{recipe}_{i + 1}")

            out[f"train_{recipe}_{i + 1}"] = make
    return out


def _tiny_programs() -> dict[str, Callable[[], Program]]:
    from llrmpp_jax.experiment import load_experiment

    def tiny_train() -> Program:
        exp = load_experiment("dl3dv")
        return train_program(
            replace(exp, model=C.tiny()), exp.stages[3], "tiny_train", views=(2, 1), size=(64, 96), per_device_batch=1
        )

    return {
        "tiny_reconstruct": lambda: reconstruct_program(C.tiny(), 2, (64, 96), True, name="tiny_reconstruct"),
        "tiny_render": lambda: render_program(C.tiny(), 2, (64, 96), True, name="tiny_render"),
        "tiny_train": tiny_train,
    }


PROGRAMS: dict[str, Callable[[], Program]] = {**_paper_programs(), **_tiny_programs()}
assert tuple(PROGRAMS) == PROGRAM_NAMES, "plan/catalog.py names the programs PROGRAMS builds"


def program(name: str) -> Program:
    """The program ``name`` (a key of :data:`PROGRAMS`); one-line ``UserError`` listing them otherwise."""
    if name not in PROGRAMS:
        raise UserError(
            f"plan: unknown program {name!r}; known programs: {', '.join(PROGRAM_NAMES)} (groups: {', '.join(GROUPS)})"
        )
    return PROGRAMS[name]()
