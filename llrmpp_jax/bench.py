"""``llrmpp bench``: the project's benchmarks at one scale, as JSON.

:func:`run_benchmarks` runs, each in its own process (so one's memory and compile caches
do not colour the next):

* ``attention`` -- :func:`attention_benchmark` (here, entry ``experiments/bench_attention.py``):
  XLA's memory analysis of one global-attention forward+backward, plain (``"xla"``) vs
  ``"blockwise"``, compile only, and compile / run times of the blockwise kernel.
* ``scan``, ``splat`` -- ``experiments/bench_{scan,splat}.py``.
* ``model`` -- the paper's Table-1 reconstruction and render cases
  (:mod:`llrmpp_jax.bench_paper`, entry ``experiments/bench_model.py``).
* ``paper_step`` -- the stage-4 training step executed (``experiments/bench_paper_step.py``).

Each entry gets the scale's arguments (:data:`SCALES`), syncs with ``block_until_ready``
and reports compile time apart from run time; the measuring tools (synced timing, XLA's
cost analysis, traced FLOP counts, fractions of the card's bf16 peak) are in
:mod:`llrmpp_jax.bench_measure`.

The summary JSON (``<out>/bench.json``) records the device, library versions, load
average before and after, and each benchmark's own JSON (also written beside it).
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import time

from llrmpp_jax.bench_measure import environment, timed
from llrmpp_jax.experiment import EXPERIMENTS_DIR as EXPERIMENTS

BENCHMARKS = ("attention", "scan", "splat", "model", "paper_step")

# scale -> benchmark -> command-line arguments of experiments/bench_<benchmark>.py.
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
        "attention": ["--lengths", "8192", "32768", "131072", "261122", "--run-lengths", "8192", "32768", "131072",
                      "--dtype", "bfloat16"],
        "scan": ["--preset", "full"],
        "splat": [],
        "model": ["--scale", "paper"],
        # cuDNN only: the blockwise kernel's step (67 s on an H200) would double the part's time.
        "paper_step": ["--scale", "paper", "--impls", "cudnn", "--steps", "1", "--timeout", "480"],
    },
}


def attention_fwd_bwd(implementation: str, block: int = 512):
    """``(q, k, v, cotangent) -> (dq, dk, dv)`` of one global attention (a training step's
    share of it): forward and backward through :func:`multi_head_attention`."""
    import jax

    from llrmpp_jax.nn.attention import multi_head_attention

    def step(q, k, v, cot):
        _, vjp = jax.vjp(
            lambda q, k, v: multi_head_attention(q, k, v, implementation=implementation,
                                                 block_q=block, block_k=block), q, k, v)
        return vjp(cot)

    return step


def _one_line(e: Exception) -> str:
    return f"{type(e).__name__}: {(str(e).splitlines() or [''])[0][:300]}"


def attention_benchmark(lengths=(8192, 32768, 131072), run_lengths=(4096, 8192), heads: int = 12,
                        head_dim: int = 64, block: int = 512, dtype: str = "float32", repeats: int = 2) -> dict:
    """Memory of one attention fwd+bwd ``[1, L, heads, head_dim]`` (the paper backbone's
    12 x 64 heads), plain vs blockwise (and cuDNN on a GPU), from XLA's ``memory_analysis()``
    of the compiled program (compile only: nothing is allocated); then compile and run times
    of the memory-efficient kernels (blockwise; cuDNN on a GPU) at ``run_lengths``.
    ``temp_bytes`` is XLA's scratch on top of the arguments (q, k, v, cotangent) and outputs
    (dq, dk, dv). A kernel that cannot be compiled or run at a length gets ``{"failed": ...}``
    in its row (on a GPU, XLA's compile of the plain kernel allocates its [L, L] buffers to
    autotune: 768 GiB at L = 131k on an H200) and the other rows go on."""
    import jax
    import jax.numpy as jnp

    dt = jnp.dtype(dtype)
    impls = ("xla", "blockwise", "cudnn") if jax.default_backend() == "gpu" else ("xla", "blockwise")
    rows = []
    for length in lengths:
        x = jax.ShapeDtypeStruct((1, length, heads, head_dim), dt)
        row = {"L": length, "logits_bytes_per_copy": heads * length * length * 4}
        for impl in impls:
            t0 = time.perf_counter()
            try:
                ma = jax.jit(attention_fwd_bwd(impl, block)).lower(x, x, x, x).compile().memory_analysis()
            except Exception as e:  # noqa: BLE001 -- recorded, the next row goes on
                row[impl] = {"failed": _one_line(e), "compile_s": time.perf_counter() - t0}
                continue
            row[impl] = {"temp_bytes": int(ma.temp_size_in_bytes),
                         "argument_bytes": int(ma.argument_size_in_bytes),
                         "output_bytes": int(ma.output_size_in_bytes),
                         "compile_s": time.perf_counter() - t0}
        rows.append(row)
    runs = []
    key = jax.random.key(0)
    for length in run_lengths:
        q, k, v, cot = (jax.random.normal(kk, (1, length, heads, head_dim), dt) for kk in jax.random.split(key, 4))
        run = {"L": length}
        for impl in impls[1:]:
            try:
                run[impl] = timed(attention_fwd_bwd(impl, block), q, k, v, cot, repeats=repeats)
            except Exception as e:  # noqa: BLE001
                run[impl] = {"failed": _one_line(e)}
        runs.append(run)
    ok = [r for r in rows if "temp_bytes" in r["blockwise"]]
    return {"heads": heads, "head_dim": head_dim, "block": block, "dtype": dtype, "memory": rows,
            "blockwise_temp_bytes_per_token": {r["L"]: r["blockwise"]["temp_bytes"] / r["L"] for r in ok},
            "runs": runs}


def run_benchmarks(scale: str, out_dir: str, only: tuple[str, ...] = BENCHMARKS,
                   views: tuple[int, ...] | None = None, size: tuple[int, int] | None = None) -> dict:
    """Run the ``only`` benchmarks at ``scale`` (a key of :data:`SCALES`); write
    ``<out_dir>/bench_<name>.json`` for each and ``<out_dir>/bench.json`` (the summary).
    ``views`` (input view counts) and ``size`` (H, W) replace the ``model`` benchmark's
    (:mod:`llrmpp_jax.bench_paper`). Bad input is a one-line ``ValueError`` before anything runs."""
    if scale not in SCALES:
        raise ValueError(f"bench: unknown scale {scale!r}, expected one of {sorted(SCALES)}")
    unknown = [b for b in only if b not in BENCHMARKS]
    if unknown:
        raise ValueError(f"bench: unknown benchmark(s) {unknown}, expected a subset of {list(BENCHMARKS)}")
    model_args: list[str] = []
    if views is not None or size is not None:
        from llrmpp_jax.bench_paper import bench_scale, check_case

        if "model" not in only:
            raise ValueError(f"bench: --views/--size set the model benchmark's cases, which --only {','.join(only)} "
                             "leaves out")
        s = bench_scale(scale)
        views, size = views or s.views, size or (s.height, s.width)
        check_case(s.model, views, *size)
        model_args = ["--views", ",".join(map(str, views)), "--size", f"{size[0]}x{size[1]}"]
    os.makedirs(out_dir, exist_ok=True)
    summary = {"scale": scale, "environment_at_start": environment(), "benchmarks": {}}
    for name in only:
        out = os.path.join(out_dir, f"bench_{name}.json")
        cmd = [sys.executable, os.path.join(EXPERIMENTS, f"bench_{name}.py"), *SCALES[scale][name],
               *(model_args if name == "model" else []), "--out", out]
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
