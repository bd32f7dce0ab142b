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
from collections.abc import Callable, Iterator, Sequence
from concurrent.futures import ProcessPoolExecutor, as_completed
from dataclasses import dataclass
from typing import Any

import numpy as np

from llrmpp_jax import config as C
from llrmpp_jax.ablation.rows import Ordering, Variant, selected
from llrmpp_jax.ablation.scales import Scale
from llrmpp_jax.ablation.scoring import held_out_samples, references, row_scores, time_model
from llrmpp_jax.ablation.stats import compare, summarise
from llrmpp_jax.ablation.training import train
from llrmpp_jax.metrics import load_lpips_params
from llrmpp_jax.nn.backbone import count_params


@dataclass
class TableRun:
    """Everything a notebook shows: the ``results`` of each selected row, the
    ``references`` (untrained chosen row, baselines), per-row mean training ``curves``
    (loss per step, averaged over seeds), the wall ``seconds`` of the whole table and the
    ``comparisons`` of the paper's orderings (:func:`~llrmpp_jax.ablation.stats.compare`,
    each with what ``stopped`` its seeds)."""

    scale: Scale
    results: list[dict[str, Any]]
    references: list[dict[str, Any]]
    curves: dict[int, list[float]]
    seconds: float
    comparisons: list[dict[str, Any]] = dataclasses.field(default_factory=list)


@functools.cache
def _held_out(scale: Scale, cfg: C.ModelConfig) -> tuple[dict[str, np.ndarray], ...]:
    """:func:`~llrmpp_jax.ablation.scoring.held_out_samples` of a row of ``cfg``, made once
    per process."""
    return tuple(held_out_samples(cfg, scale))


@functools.cache
def _lpips_params(scale: Scale) -> Any:
    """The LPIPS weights when ``scale.lpips``, else None; loaded once per process."""
    return load_lpips_params() if scale.lpips else None


@dataclass
class SeedRun:
    """One row trained at one seed and scored on the held-out scenes: the
    :func:`~llrmpp_jax.ablation.scoring.row_scores` ``scores``, the :class:`Trained` ``losses``, ``seconds`` and
    ``dropped``, and its ``params`` when asked for (the row's timings use seed 0's)."""

    scores: dict[str, float]
    losses: np.ndarray
    seconds: float
    dropped: int
    params: dict | None


def run_seed(cfg: C.ModelConfig, scale: Scale, variant: Variant, seed: int, keep_params: bool = False) -> SeedRun:
    """:func:`train` ``cfg`` at ``seed`` and score it on the held-out scenes
    (:func:`~llrmpp_jax.ablation.scoring.row_scores`)."""
    trained = train(cfg, scale, variant, seed)
    scores = row_scores(trained.params, cfg, _held_out(scale, cfg), _lpips_params(scale))
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


Job = tuple[int, C.ModelConfig, Variant, int]  # (row, config, variant, seed)
# The interval a sequential table decides on at each look (run_table's docstring).
SEQUENTIAL_CONFIDENCE = 0.99


@contextlib.contextmanager
def _runner(scale: Scale) -> Iterator[Callable[[Sequence[Job]], Iterator[tuple[int, int, SeedRun]]]]:
    """A function that runs ``(row, cfg, variant, seed)`` jobs with :func:`run_seed`,
    yielding ``(row, seed, SeedRun)`` as they finish: in this process when
    ``scale.workers`` is 1, else on one pool (kept for every round of a sequential table) of
    ``scale.workers`` spawned processes, each pinned to its own core (by
    ``os.sched_setaffinity``, the worker ``i`` on the ``i``-th core this process may use).
    Seed 0's params come back for the row's timings."""
    if scale.workers == 1:

        def run_here(jobs: Sequence[Job]) -> Iterator[tuple[int, int, SeedRun]]:
            for row, cfg, variant, seed in jobs:
                yield row, seed, run_seed(cfg, scale, variant, seed, keep_params=seed == 0)

        yield run_here
        return
    ctx = multiprocessing.get_context("spawn")  # fork after JAX has started threads is unsafe
    cores = ctx.Queue()
    allowed = sorted(os.sched_getaffinity(0))
    for i in range(scale.workers):
        cores.put(allowed[i % len(allowed)])
    with ProcessPoolExecutor(scale.workers, mp_context=ctx, initializer=_pin_to_core, initargs=(cores,)) as pool:

        def run_on_pool(jobs: Sequence[Job]) -> Iterator[tuple[int, int, SeedRun]]:
            # A Variant's build function may be a notebook lambda (not picklable); workers
            # need only its loss weights.
            with _main_hidden():  # workers start on submit (spawn context)
                futures = {
                    pool.submit(run_seed, cfg, scale, dataclasses.replace(variant, build=None), seed, seed == 0): (
                        row,
                        seed,
                    )
                    for row, cfg, variant, seed in jobs
                }
            for future in as_completed(futures):
                row, seed = futures[future]
                yield row, seed, future.result()

        yield run_on_pool


def _scores(index: int, v: Variant, per_seed: Sequence[SeedRun]) -> dict[str, Any]:
    """A row's labels, paper numbers and its scores summarised over its seeds (in order)."""
    tails = [r.losses[-max(1, len(r.losses) // 10) :] for r in per_seed]
    return {
        "row": index,
        **v.labels,
        "chosen": v.chosen,
        "paper": dict(v.paper),
        "status": "ok",
        "seeds": len(per_seed),
        **summarise(
            [
                {
                    **r.scores,
                    "train_s": r.seconds,
                    "train_dropped": float(r.dropped),
                    "final_loss": float(np.mean(tail)) if len(tail) else float("nan"),
                }
                for r, tail in zip(per_seed, tails)
            ]
        ),
    }


def _next_round(
    runs: dict[int, dict[int, SeedRun]],
    variants: Sequence[Variant],
    orderings: Sequence[Ordering],
    scale: Scale,
    stops: dict[str, str],
    out_of_time: bool,
) -> list[tuple[int, int]]:
    """The ``(row, seed)`` trainings of the next sequential round: one more seed for both
    rows of every ordering still unresolved; orderings that stop get their reason in
    ``stops``."""
    results = [_scores(i, variants[i], [r[s] for s in sorted(r)]) for i, r in runs.items()]
    wanted: dict[int, int] = {}
    for c in compare(results, orderings, SEQUENTIAL_CONFIDENCE):
        if c["ordering"] in stops:
            continue
        n = c.get("seeds", 0)
        if c["verdict"] == "not run":
            stops[c["ordering"]] = "a row did not run"
        elif c["verdict"] != "not resolved":
            stops[c["ordering"]] = f"resolved at {n} seeds"
        elif n >= scale.max_seeds:
            stops[c["ordering"]] = f"the cap of {scale.max_seeds} seeds"
        elif out_of_time:
            stops[c["ordering"]] = f"the {scale.budget_min:.0f}-minute budget, at {n} seeds"
        else:
            for row in (c["better"], c["worse"]):
                if len(runs[row]) == n:
                    wanted[row] = n
    return sorted(wanted.items())


def run_table(variants: Sequence[Variant], scale: Scale, orderings: Sequence[Ordering] = ()) -> TableRun:
    """Train (once per seed), evaluate and time each selected row (:func:`selected`); rows
    without a config are kept with ``status`` saying why. One result dict per row: its
    labels, ``paper`` numbers, ``status``, ``seeds`` (how many it ran), and for run rows
    ``params``, ``decoder_params``, ``decoder_dim`` (None in colour mode), ``train_s`` (per
    seed, mean), ``final_loss``, ``train_dropped``, the
    :func:`~llrmpp_jax.ablation.scoring.row_scores` summarised over seeds and the :func:`time_model` timings (seed
    0's params, timed in this process after every training has finished, so no worker competes with them).

    Every row runs ``scale.seeds`` seeds; seed ``s`` gives every row the same training
    batches and every row is scored on the same held-out scenes, so two rows' difference at
    a seed is paired (common random numbers). With ``scale.max_seeds`` > ``scale.seeds``
    the table is sequential: after each round, both rows of every ``orderings`` entry whose
    paired 95% interval still contains 0 get the next seed, until it resolves, reaches
    ``max_seeds``, or the table has run ``scale.budget_min`` minutes; each entry of
    ``comparisons`` says which stopped it (``stopped``). Looking at the interval after every
    round and stopping when it excludes 0 would call a zero difference resolved far more
    often than 5% of the time: 16.7% with 95% intervals at each of the looks from 3 to 10
    seeds (a simulation of normal differences, 200k tables). A sequential table therefore
    decides on :data:`SEQUENTIAL_CONFIDENCE` (99%) intervals at every look, 4.3% overall in
    the same simulation (Pocock's idea: one stricter level for every look), and reports
    those intervals.

    The trainings of a round run ``scale.workers`` at a time (:func:`_runner`); ``train_s``
    is then the time of a training that shared the machine with the other workers, each on
    one core."""
    t_start = time.perf_counter()
    rows = selected(variants)
    configs = {index: v.build(scale.base) for index, v in rows if v.build is not None}
    runs: dict[int, dict[int, SeedRun]] = {index: {} for index in configs}
    stops: dict[str, str] = {}
    todo = [(index, seed) for index in configs for seed in range(scale.seeds)]
    with _runner(scale) as run:
        while todo:
            jobs = [(index, configs[index], variants[index], seed) for index, seed in todo]
            for done, (index, seed, r) in enumerate(run(jobs), 1):
                runs[index][seed] = r
                progress(
                    f"row {index} {variants[index].labels} seed {seed}: PSNR {r.scores['psnr']:.2f}, "
                    f"trained in {r.seconds:.0f} s ({done}/{len(jobs)} of this round, "
                    f"{(time.perf_counter() - t_start) / 60:.1f} min)"
                )
            if scale.max_seeds <= scale.seeds or not orderings:
                break
            minutes = (time.perf_counter() - t_start) / 60
            todo = _next_round(
                runs,
                variants,
                orderings,
                scale,
                stops,
                out_of_time=scale.budget_min is not None and minutes >= scale.budget_min,
            )
            if todo:
                progress(f"round: {len(todo)} more trainings for unresolved orderings ({minutes:.1f} min)")
    results, curves = [], {}
    for index, v in rows:
        if index not in configs:
            results.append(
                {"row": index, **v.labels, "chosen": v.chosen, "paper": dict(v.paper), "status": f"not run: {v.note}"}
            )
            continue
        cfg, per_seed = configs[index], [runs[index][seed] for seed in sorted(runs[index])]
        samples = _held_out(scale, cfg)
        row = _scores(index, v, per_seed)
        row.update(
            time_model(per_seed[0].params, cfg, scale, samples[0]),  # pyright: ignore[reportArgumentType] -- a finished run has its params
            params=count_params(per_seed[0].params),
            decoder_params=count_params(per_seed[0].params.get("decoder", {})),  # pyright: ignore[reportOptionalMemberAccess] -- a finished run has its params
            decoder_dim=cfg.decoder.dim if cfg.head.mode == "feature" else None,
        )
        curves[index] = np.mean([r.losses for r in per_seed], axis=0).tolist()
        results.append(row)
    sequential = scale.max_seeds > scale.seeds
    comparisons = compare(results, orderings, SEQUENTIAL_CONFIDENCE if sequential else 0.95)
    for c in comparisons:
        c["stopped"] = stops.get(c["ordering"], f"fixed {scale.seeds} seeds")
    runnable = [v for index, v in rows if index in configs]
    chosen = [v for v in runnable if v.chosen] or runnable
    refs = []
    if chosen:
        cfg = chosen[0].build(scale.base)  # pyright: ignore[reportOptionalCall] -- runnable rows have a build
        refs = references(cfg, scale, _held_out(scale, cfg), _lpips_params(scale))
    return TableRun(scale, results, refs, curves, time.perf_counter() - t_start, comparisons)
