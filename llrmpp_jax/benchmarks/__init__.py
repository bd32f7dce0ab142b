"""Benchmarks, each runnable as ``python -m llrmpp_jax.benchmarks.<name>`` with its own flags
(``--help``); ``llrmpp bench`` runs them at one scale (:mod:`~llrmpp_jax.benchmarks.suite`).

* :mod:`~llrmpp_jax.benchmarks.attention`, :mod:`~llrmpp_jax.benchmarks.scan`,
  :mod:`~llrmpp_jax.benchmarks.splat` -- global attention, the SSD scan, the splatter;
* :mod:`~llrmpp_jax.benchmarks.model` -- the paper's Table-1 cases (reconstruct, render;
  :mod:`~llrmpp_jax.benchmarks.paper`);
* :mod:`~llrmpp_jax.benchmarks.paper_step` -- the paper's stage-4 training step executed;
* :mod:`~llrmpp_jax.benchmarks.measure` -- what they measure with (synced timing, FLOPs,
  memory, the environment record).
"""
