"""Running a table: :func:`run_table` trains every selected row once per seed (in this
process, or on a pool of single-core worker processes), scores and times it, and adds the
references; :class:`TableRun` is what a notebook shows."""

from __future__ import annotations

import contextlib
import dataclasses
import functools
import multiprocessing
import os
import sys
import time
import types
from collections.abc import Iterator, Sequence
from concurrent.futures import ProcessPoolExecutor, as_completed
from dataclasses import dataclass
from typing import Any

import numpy as np

from llrmpp_jax import config as C
from llrmpp_jax.ablation.rows import Variant, selected
from llrmpp_jax.ablation.scales import Scale
from llrmpp_jax.ablation.scoring import eval_samples, evaluate, references, time_model
from llrmpp_jax.ablation.stats import summarise
from llrmpp_jax.ablation.training import train
from llrmpp_jax.metrics import load_lpips_params
from llrmpp_jax.nn.backbone import count_params

@dataclass
class TableRun:
    """Everything a notebook shows: the ``results`` of each selected row, the
    ``references`` (untrained chosen row, baselines), per-row mean training ``curves``
    (loss per step, averaged over seeds) and the wall ``seconds`` of the whole table."""

    scale: Scale
    results: list[dict[str, Any]]
    references: list[dict[str, Any]]
    curves: dict[int, list[float]]
    seconds: float


@functools.lru_cache(maxsize=None)
def _held_out(scale: Scale, depth: bool) -> tuple[dict[str, np.ndarray], ...]:
    """:func:`eval_samples`, made once per process."""
    return tuple(eval_samples(scale, depth))


@functools.lru_cache(maxsize=None)
def _lpips_params(scale: Scale) -> Any:
    """The LPIPS weights when ``scale.lpips``, else None; loaded once per process."""
    return load_lpips_params() if scale.lpips else None


@dataclass
class SeedRun:
    """One row trained at one seed and scored on the held-out scenes: the
    :func:`evaluate` ``scores``, the :class:`Trained` ``losses``, ``seconds`` and
    ``dropped``, and its ``params`` when asked for (the row's timings use seed 0's)."""

    scores: dict[str, float]
    losses: np.ndarray
    seconds: float
    dropped: int
    params: dict | None


def run_seed(cfg: C.ModelConfig, scale: Scale, variant: Variant, seed: int, keep_params: bool = False) -> SeedRun:
    """:func:`train` ``cfg`` at ``seed`` and :func:`evaluate` it on the held-out scenes."""
    trained = train(cfg, scale, variant, seed)
    scores = evaluate(trained.params, cfg, scale, _held_out(scale, "depth" in cfg.outputs), _lpips_params(scale))
    return SeedRun(scores, trained.losses, trained.seconds, trained.dropped, trained.params if keep_params else None)


def _pin_to_core(cores: Any) -> None:
    """Pool initializer: bind this worker to one core before JAX sizes its thread pool."""
    os.sched_setaffinity(0, {cores.get()})


@contextlib.contextmanager
def _main_hidden() -> Iterator[None]:
    """Hide ``__main__`` while pool workers start: multiprocessing's spawn re-runs the main
    script in every worker, which for a table run as ``python notebooks/table*.py`` would be
    the whole table again. Workers need only this package (in a notebook kernel, ``__main__``
    is no script and nothing changes)."""
    main = sys.modules["__main__"]
    sys.modules["__main__"] = types.ModuleType("__main__")
    try:
        yield
    finally:
        sys.modules["__main__"] = main


def progress(text: str) -> None:
    """Print ``text`` in the notebook, and, when ``notebooks/_execute.py`` runs it
    (``LLRMPP_NOTEBOOK_ECHO``), on the kernel's own stderr: the terminal of
    ``make notebooks``, which shows cell outputs only at the end."""
    print(text, flush=True)
    if os.environ.get("LLRMPP_NOTEBOOK_ECHO") and sys.__stderr__ is not None and sys.stderr is not sys.__stderr__:
        print(text, file=sys.__stderr__, flush=True)


def _run_seeds(jobs: Sequence[tuple[int, C.ModelConfig, Variant, int]], scale: Scale
               ) -> Iterator[tuple[int, int, SeedRun]]:
    """Run each ``(row, cfg, variant, seed)`` job with :func:`run_seed`, yielding
    ``(row, seed, SeedRun)`` as they finish: in this process when ``scale.workers`` is 1,
    else on a pool of ``scale.workers`` spawned processes, each pinned to its own core (by
    ``os.sched_setaffinity``, the worker ``i`` on the ``i``-th core this process may use).
    Seed 0's params come back for the row's timings."""
    if scale.workers == 1:
        for row, cfg, variant, seed in jobs:
            yield row, seed, run_seed(cfg, scale, variant, seed, keep_params=seed == 0)
        return
    ctx = multiprocessing.get_context("spawn")  # fork after JAX has started threads is unsafe
    cores = ctx.Queue()
    allowed = sorted(os.sched_getaffinity(0))
    for i in range(scale.workers):
        cores.put(allowed[i % len(allowed)])
    with ProcessPoolExecutor(scale.workers, mp_context=ctx, initializer=_pin_to_core, initargs=(cores,)) as pool:
        # A Variant's build function may be a notebook lambda (not picklable); workers need
        # only its loss weights.
        with _main_hidden():  # workers start on submit (spawn context)
            futures = {pool.submit(run_seed, cfg, scale, dataclasses.replace(variant, build=None), seed, seed == 0):
                       (row, seed) for row, cfg, variant, seed in jobs}
        for future in as_completed(futures):
            row, seed = futures[future]
            yield row, seed, future.result()


def run_table(variants: Sequence[Variant], scale: Scale) -> TableRun:
    """Train (once per seed), evaluate and time each selected row (:func:`selected`); rows
    without a config are kept with ``status`` saying why. One result dict per row: its
    labels, ``paper`` numbers, ``status``, and for run rows ``params``, ``decoder_params``,
    ``decoder_dim`` (None in colour mode), ``train_s`` (per seed, mean), ``final_loss``,
    ``train_dropped``, the :func:`evaluate` scores summarised over seeds by
    :func:`_summarise` and the :func:`time_model` timings (seed 0's params, timed in this
    process after every training has finished, so no worker competes with them).

    The trainings of all rows and seeds run ``scale.workers`` at a time
    (:func:`_run_seeds`); ``train_s`` is then the time of a training that shared the
    machine with the other workers, each on one core."""
    t_start = time.perf_counter()
    rows = selected(variants)
    configs = {index: v.build(scale.base) for index, v in rows if v.build is not None}
    jobs = [(index, configs[index], v, seed) for index, v in rows if index in configs for seed in range(scale.seeds)]
    runs: dict[int, dict[int, SeedRun]] = {index: {} for index in configs}
    for index, seed, r in _run_seeds(jobs, scale):
        runs[index][seed] = r
        progress(f"row {index} {variants[index].labels} seed {seed}: PSNR {r.scores['psnr']:.2f}, "
                  f"trained in {r.seconds:.0f} s ({sum(map(len, runs.values()))}/{len(jobs)} done, "
                  f"{(time.perf_counter() - t_start) / 60:.1f} min)")
    results, curves = [], {}
    for index, v in rows:
        row: dict[str, Any] = {"row": index, **v.labels, "chosen": v.chosen, "paper": dict(v.paper)}
        if index not in configs:
            results.append({**row, "status": f"not run: {v.note}"})
            continue
        cfg, per_seed = configs[index], [runs[index][seed] for seed in range(scale.seeds)]
        samples = _held_out(scale, "depth" in cfg.outputs)
        row.update(time_model(per_seed[0].params, cfg, scale, samples[0]),
                   params=count_params(per_seed[0].params),
                   decoder_params=count_params(per_seed[0].params.get("decoder", {})),
                   decoder_dim=cfg.decoder.dim if cfg.head.mode == "feature" else None)
        tails = [r.losses[-max(1, len(r.losses) // 10):] for r in per_seed]
        row.update(status="ok", seeds=scale.seeds, **summarise([
            {**r.scores, "train_s": r.seconds, "train_dropped": float(r.dropped),
             "final_loss": float(np.mean(tail)) if len(tail) else float("nan")} for r, tail in zip(per_seed, tails)]))
        curves[index] = np.mean([r.losses for r in per_seed], axis=0).tolist()
        results.append(row)
    runnable = [v for index, v in rows if index in configs]
    chosen = [v for v in runnable if v.chosen] or runnable
    refs = []
    if chosen:
        cfg = chosen[0].build(scale.base)
        refs = references(cfg, scale, _held_out(scale, "depth" in cfg.outputs), _lpips_params(scale))
    return TableRun(scale, results, refs, curves, time.perf_counter() - t_start)
