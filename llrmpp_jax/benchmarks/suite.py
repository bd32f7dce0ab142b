"""``llrmpp bench``: the project's benchmarks at one scale, as JSON.

:func:`run_benchmarks` runs each of :data:`BENCHMARKS` in its own process (so one's memory
and compile caches do not colour the next), as ``python -m llrmpp_jax.benchmarks.<name>``:

* ``attention`` -- :mod:`~llrmpp_jax.benchmarks.attention`: XLA's memory analysis of one
  global-attention forward+backward, plain (``"xla"``) vs ``"blockwise"``, compile only, and
  compile / run times of the blockwise kernel.
* ``scan``, ``splat`` -- :mod:`~llrmpp_jax.benchmarks.scan`, :mod:`~llrmpp_jax.benchmarks.splat`.
* ``model`` -- the paper's Table-1 reconstruction and render cases
  (:mod:`~llrmpp_jax.benchmarks.paper`, entry :mod:`~llrmpp_jax.benchmarks.model`).
* ``paper_step`` -- the stage-4 training step executed (:mod:`~llrmpp_jax.benchmarks.paper_step`).

Each entry gets the scale's arguments (:data:`SCALES`), syncs with ``block_until_ready``
and reports compile time apart from run time; the measuring tools (synced timing, XLA's
cost analysis, traced FLOP counts, fractions of the card's bf16 peak) are in
:mod:`llrmpp_jax.benchmarks.measure`.

The summary JSON (``<out>/bench.json``) records the device, library versions, load
average before and after, and each benchmark's own JSON (also written beside it).
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import time

from llrmpp_jax.benchmarks.measure import environment
from llrmpp_jax.errors import UserError

BENCHMARKS = ("attention", "scan", "splat", "model", "paper_step")

# scale -> benchmark -> command-line arguments of python -m llrmpp_jax.benchmarks.<benchmark>.
SCALES: dict[str, dict[str, list[str]]] = {
    # A 2-core CPU box in minutes: memory analysis up to 131k tokens (compile only), runs to 8k.
    "cpu": {
        "attention": ["--lengths", "8192", "32768", "131072", "--run-lengths", "4096", "8192"],
        "scan": ["--preset", "cpu"],
        "splat": ["--quick", "--repeats", "2"],
        "model": ["--scale", "cpu"],
        "paper_step": ["--scale", "cpu"],
    },
    # One accelerator: the paper's sequence lengths run.
    "paper": {
        "attention": [
            "--lengths",
            "8192",
            "32768",
            "131072",
            "261122",
            "--run-lengths",
            "8192",
            "32768",
            "131072",
            "--dtype",
            "bfloat16",
        ],
        "scan": ["--preset", "full"],
        "splat": [],
        "model": ["--scale", "paper"],
        # cuDNN only: the blockwise kernel's step, slower than cuDNN's, would double the part's time.
        "paper_step": ["--scale", "paper", "--impls", "cudnn", "--steps", "1", "--timeout", "480"],
    },
}


def run_benchmarks(
    scale: str,
    out_dir: str,
    only: tuple[str, ...] = BENCHMARKS,
    views: tuple[int, ...] | None = None,
    size: tuple[int, int] | None = None,
) -> dict:
    """Run the ``only`` benchmarks at ``scale`` (a key of :data:`SCALES`); write
    ``<out_dir>/bench_<name>.json`` for each and ``<out_dir>/bench.json`` (the summary).
    ``views`` (input view counts) and ``size`` (H, W) replace the ``model`` benchmark's
    (:mod:`llrmpp_jax.benchmarks.paper`). Bad input is a one-line ``UserError`` before anything runs."""
    if scale not in SCALES:
        raise UserError(f"bench: unknown scale {scale!r}, expected one of {sorted(SCALES)}")
    unknown = [b for b in only if b not in BENCHMARKS]
    if unknown:
        raise UserError(f"bench: unknown benchmark(s) {unknown}, expected a subset of {list(BENCHMARKS)}")
    model_args: list[str] = []
    if views is not None or size is not None:
        from llrmpp_jax.benchmarks.paper import bench_scale, check_case

        if "model" not in only:
            raise UserError(
                f"bench: --views/--size set the model benchmark's cases, which --only {','.join(only)} leaves out"
            )
        s = bench_scale(scale)
        views, size = views or s.views, size or (s.height, s.width)
        check_case(s.model, views, *size)
        model_args = ["--views", ",".join(map(str, views)), "--size", f"{size[0]}x{size[1]}"]
    os.makedirs(out_dir, exist_ok=True)
    summary = {"scale": scale, "environment_at_start": environment(), "benchmarks": {}}
    for name in only:
        out = os.path.join(out_dir, f"bench_{name}.json")
        cmd = [
            sys.executable,
            "-m",
            f"llrmpp_jax.benchmarks.{name}",
            *SCALES[scale][name],
            *(model_args if name == "model" else []),
            "--out",
            out,
        ]
        t0 = time.perf_counter()
        # Output passes through: a benchmark stopped from outside (a time limit) leaves its
        # progress lines where the caller can see how far it got.
        sys.stdout.flush()
        proc = subprocess.run(cmd)
        entry = {"command": cmd, "wall_s": time.perf_counter() - t0, "exit": proc.returncode}
        if proc.returncode == 0 and os.path.exists(out):
            with open(out) as f:
                entry["result"] = json.load(f)
        else:
            entry["error"] = f"exit {proc.returncode}, no {out} (its error is in the output above)"
        summary["benchmarks"][name] = entry
        print(f"bench {name}: exit {proc.returncode} in {entry['wall_s']:.0f} s -> {out}", flush=True)
    summary["load_average_at_end"] = list(os.getloadavg())
    with open(os.path.join(out_dir, "bench.json"), "w") as f:
        json.dump(summary, f, indent=1)
    return summary
