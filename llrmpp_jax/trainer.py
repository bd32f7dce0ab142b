"""Training an experiment in a workdir: stages, checkpoints and resume, signals, logging,
held-out evaluation around the stage loop (:func:`llrmpp_jax.train.loop.run_stage`; those
are its hooks) and the objective (:mod:`llrmpp_jax.objective`).

``train(exp, workdir)`` runs every stage of ``exp`` in order. Each stage restarts the
optimizer and schedule from the previous stage's parameters (Long-LRM's
``reset_training_state``) and checkpoints to ``workdir/checkpoints/<stage>``; a rerun
resumes from the newest verified checkpoint (parameters, optimizer, step, data position,
PRNG), so a killed run continues exactly. Steps run through the one runner
(:mod:`llrmpp_jax.train.runner`): ``jit`` of a ``shard_map`` over every device (the
``"batch"`` axis; multi-host after ``jax.distributed.initialize``).

A stage trains with :func:`optimizer_config`, :func:`stage_key` / :func:`fresh_params`,
:func:`stage_runner` and :func:`stage_batches`; the ablation notebooks' rows
(:func:`llrmpp_jax.ablation.training.train`) train with the same functions, so a row and
the same experiment through ``llrmpp train`` give the same losses step for step.

Logged: a console progress bar (loss, PSNR, steps/s, ETA), TensorBoard scalars and image
grids in ``workdir/tb``, periodic evaluation on held-out scenes.
"""

from __future__ import annotations

import contextlib
import json
import os
import time

import jax
import jax.numpy as jnp
import numpy as np
import optax
from jax.sharding import Mesh
from tqdm.auto import tqdm

from llrmpp_jax import train as T
from llrmpp_jax.array_typing import KeyArray
from llrmpp_jax.data import BatchIterator
from llrmpp_jax.data.sources import EVAL_EVERY
from llrmpp_jax.evaluate import evaluate, picture_grid
from llrmpp_jax.experiment import ExperimentConfig, StageConfig
from llrmpp_jax.experiment_data import batch_config, eval_samples, scene_source
from llrmpp_jax.model import init_params
from llrmpp_jax.objective import load_perceptual, make_loss_fn
from llrmpp_jax.train.loop import Hook, StepInfo
from llrmpp_jax.train.peers import watch_peers
from llrmpp_jax.train.workdir_lock import workdir_lock


def optimizer_config(stage: StageConfig, spike_factor: float | None = None) -> T.OptimizerConfig:
    """AdamW + warmup/cosine of one stage, the cosine over Long-LRM's 1,000,000-step horizon
    or over the stage (``StageConfig.lr_schedule``); Mamba2's per-head vectors (like
    Long-LRM's ``_no_weight_decay``) are never decayed. ``spike_factor``: the spike guard
    (``OptimizerConfig.spike_factor``; None, ``llrmpp train``'s: off)."""
    horizon = T.LONG_LRM_TRAIN_STEPS if stage.lr_schedule == "long_lrm" else stage.steps
    return T.OptimizerConfig(
        lr=stage.lr,
        warmup_steps=min(stage.warmup_steps, stage.steps),
        total_steps=horizon,
        no_decay_names=("A_log", "dt_bias", "D"),
        spike_factor=spike_factor,
    )


def stage_key(exp: ExperimentConfig, si: int) -> KeyArray:
    """The base PRNG key of stage ``si``'s train state (its loss's randomness)."""
    return jax.random.key(exp.seed + 1000 * si)


def fresh_params(exp: ExperimentConfig, si: int) -> dict:
    """Stage ``si``'s random initial parameters (float32; from :func:`stage_key`), shaped for
    its input views and resolution."""
    stage = exp.stages[si]
    h, w = stage.resize_h, stage.resize_w or stage.resize_h
    return init_params(jax.random.fold_in(stage_key(exp, si), 1), exp.model, stage.num_inputs, h, w)  # pyright: ignore[reportArgumentType] -- a training stage sets resize_h


def stage_runner(
    exp: ExperimentConfig,
    stage: StageConfig,
    vgg: dict | None,
    optimizer: optax.GradientTransformation,
    schedule: optax.Schedule,
    mesh: Mesh | None = None,
    *,
    donate: bool = True,
) -> T.Runner:
    """The runner of ``stage`` of ``exp`` (:func:`~llrmpp_jax.train.make_runner` over ``mesh``,
    default every device; ``donate``: reuse the state's buffers): its objective
    (:func:`~llrmpp_jax.objective.make_loss_fn` with the perceptual network ``vgg``),
    ``optimizer`` and ``schedule``, bf16 compute and the large-gradient guard as ``exp`` sets them."""
    step_fn = T.make_train_step(
        make_loss_fn(exp, vgg, stage),
        optimizer,
        schedule,
        compute_dtype=jnp.bfloat16 if exp.bf16 else jnp.float32,
        skip_grad_norm_above=exp.skip_grad_norm_above,
    )
    return T.make_runner(step_fn, mesh, donate=donate)


def stage_batches(exp: ExperimentConfig, si: int, start: int = 0, *, num_devices: int) -> BatchIterator:
    """Stage ``si``'s training batches from step ``start`` (this process's rows, split over
    its ``num_devices``), data seed ``exp.seed + si``."""
    return BatchIterator(
        scene_source(exp.data),
        batch_config(exp, exp.stages[si]),
        seed=exp.seed + si,
        start_step=start,
        num_devices=num_devices,
        process_index=jax.process_index(),
        process_count=jax.process_count(),
        num_workers=exp.data.workers,
        worker_processes=exp.data.worker_processes,
    )


def train(
    exp: ExperimentConfig,
    workdir: str,
    *,
    max_minutes: float | None = None,
    progress: bool = True,
    init: str | None = None,
    peer_timeout_s: float = 60.0,
) -> dict:
    """Run (or resume) every stage; returns ``{"stages": [...], "eval": summary}``.

    ``init`` (fine-tuning): a training workdir, a params folder or ``pretrained:NAME``
    (``params_io.load_params``, whose shapes must be ``exp.model``'s: ``ValueError`` naming
    the first differing path). The first stage starts from those parameters with a fresh
    optimizer instead of a random init; a stage with a checkpoint in ``workdir`` resumes from
    it as always. ``train_log.json`` records ``init``.

    The workdir is locked for the run (:mod:`llrmpp_jax.train.workdir_lock`): a second
    ``train`` on it raises ``WorkdirBusyError`` naming the holder's PID and host.

    SIGINT (Ctrl-C) or SIGTERM stops the run after the current step with a checkpoint
    (``result["stopped_by"]`` names the signal); the same call resumes from it. A second
    Ctrl-C interrupts at once.

    Multi-host: a process silent for ``peer_timeout_s`` seconds ends the others with one
    line naming it (:func:`llrmpp_jax.train.peers.watch_peers`, exit status 4); starting
    every process again resumes from the last complete checkpoint."""
    lock = workdir_lock(workdir) if jax.process_index() == 0 else contextlib.nullcontext()
    checkpoints = os.path.join(workdir, "checkpoints")
    peers = watch_peers(
        peer_timeout_s,
        resume_hint=lambda: f"start every process again to resume from the last complete checkpoint in {checkpoints}",
    )
    with lock, peers, T.stop_on_signals() as stop:
        return _train_stages(exp, workdir, stop, max_minutes=max_minutes, progress=progress, init=init)


def _train_stages(
    exp: ExperimentConfig,
    workdir: str,
    stop: T.StopRequest,
    *,
    max_minutes: float | None,
    progress: bool,
    init: str | None,
) -> dict:
    """:func:`train`'s body; ``stop`` ends it at the next step boundary, checkpointed."""
    exp.check_devices(jax.device_count())
    vgg = load_perceptual(exp)  # missing or wrong perceptual weights fail here, before any compile
    scene_source(exp.data)  # so does a missing or empty dataset
    params = None if init is None else _start_params(init, exp)  # and wrong or misfit start weights
    if exp.eval_every and exp.data.eval_reads_training_scenes and jax.process_index() == 0:
        print(
            f"note: the held-out evaluation reads the training data ({exp.data.path}): the frames it targets "
            f"(every {EVAL_EVERY}th) are left out of training; its scenes' other frames are trained on "
            "(set data.eval_path to other scenes for held-out scenes)"
        )
    os.makedirs(workdir, exist_ok=True)
    budget = max_minutes if max_minutes is not None else exp.max_minutes
    t_start = time.time()
    from tensorboardX import SummaryWriter

    writer = SummaryWriter(os.path.join(workdir, "tb")) if jax.process_index() == 0 else None
    mesh = T.make_data_mesh()
    n_local = jax.local_device_count()
    history: list[dict] = []
    starts: dict[str, int] = {}  # stage name -> the step this call began it at
    result: dict = {"stages": []}
    for si, stage in enumerate(exp.stages):
        opt_cfg = optimizer_config(stage)
        optimizer, schedule = T.make_optimizer(opt_cfg), T.make_schedule(opt_cfg)
        key = stage_key(exp, si)
        ckpt_dir = os.path.abspath(os.path.join(workdir, "checkpoints", stage.name))
        restored = None
        if os.path.isdir(ckpt_dir):  # shapes only: an incompatible checkpoint fails before compiling
            # B023: eval_shape calls each lambda at once, in this iteration.
            shapes = jax.eval_shape(lambda: fresh_params(exp, si)) if params is None else params  # noqa: B023
            template = jax.eval_shape(lambda p: T.init_train_state(p, optimizer, key), shapes)  # noqa: B023
            restored = T.restore_checkpoint(ckpt_dir, template)
        start = 0
        if restored is not None:
            state, start = restored.state, int(restored.step)
        else:
            params = fresh_params(exp, si) if params is None else params
            state = T.init_train_state(params, optimizer, key)
        starts[stage.name] = start
        if start >= stage.steps:
            params = state.params
            result["stages"].append({"stage": stage.name, "steps": start, "resumed_complete": True})
            continue
        runner = stage_runner(exp, stage, vgg, optimizer, schedule, mesh)
        it = stage_batches(exp, si, start, num_devices=n_local)
        samples, names = eval_samples(exp, stage) if exp.eval_every else ([], [])
        bar = tqdm(
            total=stage.steps,
            initial=start,
            desc=f"{exp.name}/{stage.name}",
            disable=not progress or jax.process_index() != 0,
            dynamic_ncols=True,
        )
        hooks = [_log_hook(exp, stage, bar, history, writer), _checkpoint_hook(exp, ckpt_dir, it)]
        if samples:
            hooks.append(_eval_hook(exp, stage, samples, names, writer, stop, result))
        try:
            done = runner.run(
                state,
                it,
                steps=stage.steps,
                start=start,
                hooks=hooks,
                stop=lambda: bool(stop) or budget is not None and (time.time() - t_start) / 60 > budget,
            )
        finally:
            bar.close()
            it.close()
        # stop() was asked before the step's checkpoint: a signal that came during its
        # evaluation stops the loop after the next step, checkpointed there
        if done.stopped and stop:
            tqdm.write(
                f"{stop.signal_name} received: stopped at step {done.step} of stage {stage.name};"
                " checkpoint saved, the same command resumes from it"
            )
            result["stopped_by"] = stop.signal_name
        elif done.stopped:
            tqdm.write(f"time budget of {budget} min reached at step {done.step}; checkpoint saved")
        params = T.host_copy(done.state.params)
        result["stages"].append({"stage": stage.name, "steps": done.step, "skipped_data": it.skipped})
        if done.stopped:
            break
    if writer is not None:
        writer.close()
    result["history"] = history
    result["params"] = params
    log_path = os.path.join(workdir, "train_log.json")
    earlier = _earlier_log(log_path, starts)
    with open(log_path, "w") as f:
        json.dump(
            {
                "init": init if init is not None else earlier.get("init"),
                "stages": result["stages"],
                "history": earlier["history"] + history,
                "eval": result.get("eval"),
                "evals": earlier["evals"] + result.get("evals", []),
                "stopped_by": result.get("stopped_by"),
            },
            f,
            indent=1,
        )
    return result


def _log_hook(exp: ExperimentConfig, stage: StageConfig, bar, history: list[dict], writer) -> Hook:
    """Advance the progress bar; every ``log_every`` steps and at the stage's end, log the
    step's metrics (mean over devices) to the bar, ``history`` and TensorBoard."""
    t_log = [time.time()]

    def log(info: StepInfo) -> None:
        bar.update(1)
        if info.step % exp.log_every and info.step != stage.steps:
            return
        m = {k: float(np.mean(v)) for k, v in T.host_copy(info.metrics).items()}
        rate = exp.log_every / max(time.time() - t_log[0], 1e-9)
        t_log[0] = time.time()
        bar.set_postfix(loss=f"{m['loss']:.4f}", psnr=f"{m['psnr']:.2f}", sps=f"{rate:.2f}")
        history.append({"stage": stage.name, "step": info.step, **m})
        if writer is not None:
            for k, v in m.items():
                writer.add_scalar(f"train/{k}", v, info.step)

    return log


def _checkpoint_hook(exp: ExperimentConfig, ckpt_dir: str, it: BatchIterator) -> Hook:
    """Every ``checkpoint_every`` steps and after the last: state and data position to ``ckpt_dir``."""

    def checkpoint(info: StepInfo) -> None:
        if info.step % exp.checkpoint_every == 0 or info.last:
            T.save_checkpoint(
                ckpt_dir, T.host_copy(info.state), data_state=it.state(), config=exp, keep=exp.keep_checkpoints
            )

    return checkpoint


def _eval_hook(
    exp: ExperimentConfig,
    stage: StageConfig,
    samples: list[dict],
    names: list[str],
    writer,
    stop: T.StopRequest,
    result: dict,
) -> Hook:
    """Every ``eval_every`` steps and after the last (unless a signal stops the run: a
    scheduler's grace period is short), evaluate on the held-out ``samples``: TensorBoard
    scalars and picture grid, a console line, ``result["eval"]`` and ``result["evals"]``."""

    def held_out(info: StepInfo) -> None:
        if not (info.step % exp.eval_every == 0 or info.last and not stop):
            return
        _, summary, preds = evaluate(T.host_copy(info.state.params), exp.model_of(stage), samples, names=names)
        if writer is not None:
            for method, vals in summary.items():
                for k, v in vals.items():
                    writer.add_scalar(f"eval/{method}/{k}", v, info.step)
            writer.add_image("eval/grid", picture_grid(samples[0], preds[0]), info.step, dataformats="HWC")
        tqdm.write(
            f"[{stage.name} step {info.step}] held-out PSNR model {summary['model']['psnr']:.2f} dB"
            f" (input views re-rendered {summary['model']['input_psnr']:.2f} dB)"
        )
        result["eval"] = summary
        result.setdefault("evals", []).append({"stage": stage.name, "step": info.step, **summary["model"]})

    return held_out


def _earlier_log(path: str, starts: dict[str, int]) -> dict:
    """What the earlier calls of a resumed run logged at ``path`` (``train_log.json``), less
    the steps this call redid (those after the step it resumed each stage at): a resumed run's
    log keeps its whole history."""
    if not os.path.exists(path):
        return {"history": [], "evals": []}
    with open(path) as f:
        old = json.load(f)

    def kept(rows):
        return [r for r in rows if r["stage"] not in starts or r["step"] <= starts[r["stage"]]]

    return {**old, "history": kept(old.get("history", [])), "evals": kept(old.get("evals", []))}


def _start_params(init: str, exp: ExperimentConfig) -> dict:
    """The parameters at ``init`` as float32 host arrays, checked against ``exp.model``."""
    from llrmpp_jax.params_io import load_params

    params, _ = load_params(init, exp.model)
    return jax.tree.map(lambda x: np.asarray(x, np.float32), params)
