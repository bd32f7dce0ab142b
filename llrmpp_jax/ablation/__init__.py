"""The ablation tables (paper Tables 4-7): what the notebooks in ``notebooks/`` run.

A notebook lists its table's rows as :class:`Variant` s (row labels, a function that
turns the scale's base :class:`~llrmpp_jax.config.ModelConfig` into the row's config,
and the paper's numbers) and the paper's orderings as :class:`Ordering` s, then calls
:func:`run_table`: every runnable row is trained on procedural scenes with :func:`train`
once per seed, scored on held-out procedural scenes with :func:`row_scores` (``llrmpp
train``'s own :func:`llrmpp_jax.evaluate.evaluate` on :func:`held_out_samples`, the
:func:`llrmpp_jax.experiment_data.eval_samples` of the row's experiment) and timed with
:func:`time_model`; :func:`references` scores the untrained chosen row and the two
baselines (mean colour, nearest input view) on the same scenes. :func:`compare` turns the
per-seed scores into paired differences with 95% intervals and a verdict per ordering,
:func:`format_run` / :func:`format_orderings` print them next to the paper's numbers,
:func:`plot` draws them and :func:`save` writes everything as JSON with the :func:`revision`.

Modules: :mod:`.scales` (the scales, base models, environment), :mod:`.rows` (rows and
orderings), :mod:`.training`, :mod:`.scoring`, :mod:`.stats`, :mod:`.tables`
(:func:`run_table`), :mod:`.report` (tables, plot, save); a notebook imports this package
as ``from llrmpp_jax import ablation as A``.

Three scales (:func:`make_scale`):

* ``"smoke"``: a tiny model (:func:`llrmpp_jax.config.tiny` with a Gaussian head sized for
  procedural rooms) at 32x32, 2 input views, 40 steps, 1 seed, MSE loss only, no LPIPS.
  The numbers only show that the pipeline runs. CI runs this scale.
  Both small scales keep the procedural rooms' world units (no per-window rescaling) with
  Gaussians that reach :data:`PROCEDURAL_MAX_DIST` along their rays.
* ``"cpu"``: the demo model (the ``demo`` recipe: a 64-wide ``{4T}`` backbone, LeCun
  head and decoder init) with each table's K, F, canvas, decoder blocks and S, at 64x64 with
  4 input and 2 target views from windows of 6-10 frames of 16-frame paths (held out:
  8-frame windows), as the ``demo`` recipe trains and evaluates, batch 2,
  :data:`CPU_STEPS` steps (Table 7: 800), 3 seeds (5 for Table 6), 16
  held-out scenes with LPIPS. The budget is the pilot's (``experiments/ablation_pilot.py``, figures in
  ``notebooks/README.md``). The trainings run
  on one single-core worker process per core (:attr:`Scale.workers`, :func:`run_table`).
* ``"paper"``: the paper's architecture (:func:`paper_dl3dv` / :func:`paper_scannet`) at
  256x256 with the table's view count, MSE + 0.5 perceptual loss, LPIPS, 3 seeds; meant for
  accelerators. The data are still procedural scenes (swap ``source`` for a
  ``FileSource`` of DL3DV / ScanNet scenes to approach the paper's setting).

Environment overrides: ``LLRMPP_NOTEBOOK_SCALE`` (smoke / cpu / paper),
``LLRMPP_NOTEBOOK_STEPS`` the number of train steps, ``LLRMPP_NOTEBOOK_SEEDS`` the seeds
per row, ``LLRMPP_NOTEBOOK_WORKERS`` the trainings run at once (:attr:`Scale.workers`),
``LLRMPP_NOTEBOOK_ROWS`` a comma-separated list of row indices to run (the others
are left out of the results; ``none`` runs no row), ``LLRMPP_NOTEBOOK_OUT`` the folder
:func:`save` writes to (default ``runs/ablations``; ``make notebooks`` sets the repository's results),
``LLRMPP_NOTEBOOK_REVISION`` the code's revision that :func:`save` records (``make notebooks`` sets it).
"""

from llrmpp_jax.ablation.report import (
    format_orderings,
    format_run,
    machine,
    ordering_cells,
    plot,
    revision,
    save,
)
from llrmpp_jax.ablation.rows import METRICS, Ordering, Variant, selected
from llrmpp_jax.ablation.scales import (
    CPU_STEPS,
    CPU_WORKERS,
    EVAL_SEED,
    PROCEDURAL_DEPTH_BIAS,
    PROCEDURAL_MAX_DIST,
    SCALES,
    TRAIN_SCENES,
    Scale,
    cpu_base,
    make_scale,
    scale_name,
    smoke_base,
)
from llrmpp_jax.ablation.scoring import held_out_experiment, held_out_samples, references, row_scores, time_model
from llrmpp_jax.ablation.stats import compare, interval, seeds_to_resolve, summarise
from llrmpp_jax.ablation.tables import SeedRun, TableRun, progress, run_seed, run_table
from llrmpp_jax.ablation.training import Trained, init_model, row_experiment, row_objective, train
from llrmpp_jax.tables import Column

__all__ = [
    "CPU_STEPS",
    "CPU_WORKERS",
    "Column",
    "EVAL_SEED",
    "METRICS",
    "Ordering",
    "PROCEDURAL_DEPTH_BIAS",
    "PROCEDURAL_MAX_DIST",
    "SCALES",
    "Scale",
    "SeedRun",
    "TRAIN_SCENES",
    "TableRun",
    "Trained",
    "Variant",
    "compare",
    "cpu_base",
    "format_orderings",
    "format_run",
    "held_out_experiment",
    "held_out_samples",
    "init_model",
    "interval",
    "machine",
    "make_scale",
    "ordering_cells",
    "plot",
    "progress",
    "references",
    "revision",
    "row_experiment",
    "row_objective",
    "row_scores",
    "run_seed",
    "run_table",
    "save",
    "scale_name",
    "seeds_to_resolve",
    "selected",
    "smoke_base",
    "summarise",
    "time_model",
    "train",
]
