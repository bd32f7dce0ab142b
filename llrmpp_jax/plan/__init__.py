"""Planning a run on an accelerator from a CPU: compile a program for a named chip without
the chip, and report whether it fits, how long it took to compile and what a step should cost.

:func:`~llrmpp_jax.plan.planner.plan` compiles each (program, target) pair with the target's own compiler
(:mod:`llrmpp_jax.plan.targets`; libtpu's compile-only devices for TPU) from shapes alone
(:mod:`llrmpp_jax.plan.programs`) and returns one row per pair:

* ``compiled`` or ``error`` (the compiler's message in one line); a program over the chip's
  HBM fails to compile as it would on the chip, and its row says how much it needs
  (``needs_bytes`` from the compiler's message) instead of raising;
* ``memory``: XLA's ``memory_analysis()`` (argument, output, alias, temp bytes) and
  ``hbm_needed_bytes`` = argument + output + temp - alias against the chip's ``hbm_bytes``,
  ``fits`` and ``margin`` (the fraction of HBM left);
* ``compile_s``: lowering + compiling here, on this machine;
* ``xla_flops`` and ``xla_optimal_s``: the compiler's cost analysis (a loop body once, custom
  calls at -1: kept for reference);
* ``estimate``: :func:`llrmpp_jax.plan.hlo_cost.estimate_hlo` of the compiled module, loops
  at their trip counts, gathers and scatters at the chip's calibrated per-row rates
  (:func:`chip_model`);
* ``model_flops`` (matrix products of the computation, per device) and ``matmul_limit_s`` =
  model FLOPs / the chip's bf16 peak: no program can run faster; ``peak_fraction`` = that
  limit over the estimate.

Layout: :mod:`~llrmpp_jax.plan.catalog` names the programs and groups (no JAX import, for the
command line's help), :mod:`~llrmpp_jax.plan.targets` the chips, :mod:`~llrmpp_jax.plan.programs`
builds each program from shapes, :mod:`~llrmpp_jax.plan.hlo_cost` estimates a compiled one, and
:mod:`~llrmpp_jax.plan.planner` compiles and reports (:func:`~llrmpp_jax.plan.planner.plan`).
"""
