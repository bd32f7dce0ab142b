"""Benchmark the SSD scans: chunked (associative / sequential inter-chunk step), fused
(one lax.scan over chunks, at its own chunk size ``--fused-chunk``), dense inter-chunk form
and the sequential reference, forward and forward+backward.

Defaults are the paper's per-block sizes (D=768 -> d_inner 1536, headdim 64 -> 24 heads,
d_state 256, chunk 256, ngroups 1, batch 1) at L in {4096, 16384, 65536}: the full sweep,
for accelerators. On a small CPU box use the reduced preset::

    python -m llrmpp_jax.benchmarks.scan --preset cpu          # ~ 10 minutes on 2 cores
    python -m llrmpp_jax.benchmarks.scan --out /tmp/scan.json  # full sweep (GPU/TPU)

Writes JSON (``--out``): device, sizes, a jitted matmul's GFLOP/s measured in the same run
(per L, interleaved with the scans: every round runs the matmul and each scan once, so a
busy shared machine loads all of them alike), and per (L, method, pass) the median/min
wall time, compile time, analytic GFLOP and
achieved GFLOP/s (also as a fraction of the matmul rate), and a ``summary`` per L: the
sequential / chunked forward time ratio and the chunked scan's fraction of the matmul rate.
Runs predicted to need more than ``--mem-limit-gb`` of activations are skipped and
recorded as such. The sequential forward at L > ``--sequential-slice`` is timed on the
first ``slice`` tokens and scaled by ``L / slice`` (``extrapolated_from_L`` in its row):
it is a ``lax.scan`` whose every step costs the same, so its time is linear in L.

FLOP model (multiply-add = 2 FLOP, matmuls only; elementwise work is not counted): per
chunk of Q tokens, ``C.B`` 2*Q^2*g*n, scores@x 2*Q^2*nh*P, chunk states and state->output
2*Q*nh*P*n each; the dense inter-chunk step adds 2*c^2*nh*P*n for c chunks. The
sequential recurrence is counted as 6*L*nh*P*n (decay, outer product, add, read-out).
Forward+backward is counted as 3x forward (the usual two matmuls per forward matmul).
"""

from __future__ import annotations

import argparse
import functools
import json
import os
import platform
import statistics
import time
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from llrmpp_jax.nn import ssd
from llrmpp_jax.nn.ssd import ssd_dense, ssd_scan, ssd_sequential

# name -> f(x, dt, A, B, C, D, chunk_size)
METHODS = {
    "chunked": lambda x, dt, A, B, C, D, Q: ssd_scan(x, dt, A, B, C, chunk_size=Q, D=D),
    "chunked_scan_states": lambda x, dt, A, B, C, D, Q: ssd_scan(
        x, dt, A, B, C, chunk_size=Q, D=D, inter_chunk="sequential"
    ),
    "fused": lambda x, dt, A, B, C, D, Q: ssd_scan(x, dt, A, B, C, chunk_size=Q, D=D, inter_chunk="fused"),
    "dense": lambda x, dt, A, B, C, D, Q: ssd_dense(x, dt, A, B, C, chunk_size=Q, D=D),
    "sequential": lambda x, dt, A, B, C, D, Q: ssd_sequential(x, dt, A, B, C, D=D),
}
PRESETS: dict[str, dict[str, Any]] = {
    "full": dict(lengths=[4096, 16384, 65536], repeats=5, mem_limit_gb=60.0, matmul_n=8192),
    # 2-core CPU: paper widths; the sequential reference is timed on 4096-token slices.
    "cpu": dict(lengths=[4096, 16384, 65536], repeats=2, mem_limit_gb=4.0, matmul_n=2048),
}


def _flops(method: str, L: int, b: int, nh: int, P: int, g: int, n: int, Q: int) -> float:
    """Analytic forward matmul FLOPs (see module docstring)."""
    if method == "sequential":
        return 6.0 * b * L * nh * P * n
    c = -(-L // Q)
    per_chunk = 2 * Q * Q * g * n + 2 * Q * Q * nh * P + 2 * 2 * Q * nh * P * n
    total = b * c * per_chunk
    if method == "dense":
        total += b * 2.0 * c * c * nh * P * n
    return float(total)


def _activation_bytes(method: str, backward: bool, L: int, b: int, nh: int, P: int, g: int, n: int, Q: int) -> float:
    """Rough peak activation bytes (float32) used to skip runs that cannot fit."""
    c = -(-L // Q)
    if method == "sequential":
        # the backward of lax.scan keeps one [nh, P, n] state per time step
        return 4.0 * b * (L * nh * P * n if backward else 4 * nh * P * n + 4 * L * nh * P)
    if method == "fused":  # one chunk's blocks at a time; the backward keeps one state per chunk
        return 4.0 * (b * nh * Q * Q * 4 + b * c * nh * P * n * (1 + backward) + 4 * b * L * nh * P)
    # decay, scores (and their cotangents) [c, nh, Q, Q]; states [c, nh, P, n] (x log c levels
    # in the associative scan's backward)
    quad = b * c * nh * Q * Q
    states = b * c * nh * P * n * (2 + (np.log2(max(c, 2)) if backward else 0))
    return 4.0 * (quad * (4 if backward else 2) + states)


def _inputs(L: int, b: int, nh: int, P: int, g: int, n: int, dtype):
    rng = np.random.default_rng(0)
    x = rng.standard_normal((b, L, nh, P))
    dt = np.exp(rng.uniform(np.log(1e-3), np.log(1e-1), (b, L, nh)))
    B = rng.standard_normal((b, L, g, n))
    C = rng.standard_normal((b, L, g, n))
    A = -rng.uniform(1.0, 16.0, nh).astype(np.float32)
    cast = lambda a: jnp.asarray(a, dtype)  # noqa: E731
    return cast(x), cast(dt), jnp.asarray(A), cast(B), cast(C), jnp.ones((nh,), jnp.float32)


def _widest_span(dt: jax.Array, A: jax.Array, q: int) -> float:
    """Largest decay (nats) any head accumulates over a chunk of ``q`` tokens after its first."""
    dA = np.asarray(dt, np.float64) * np.asarray(A, np.float64)  # [b, L, nh]
    pad = -dA.shape[1] % q
    dA = np.pad(dA, [(0, 0), (0, pad), (0, 0)]).reshape(dA.shape[0], -1, q, dA.shape[2])
    return float(-dA[:, :, 1:].sum(axis=2).min())


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--out", default=os.path.join("runs", "bench", "bench_scan.json"), help="JSON file written")
    ap.add_argument("--preset", choices=sorted(PRESETS), default="full")
    ap.add_argument("--lengths", type=int, nargs="+", help="override the preset's sequence lengths")
    ap.add_argument("--methods", nargs="+", choices=sorted(METHODS), default=list(METHODS))
    ap.add_argument("--d-model", type=int, default=768)
    ap.add_argument("--expand", type=int, default=2)
    ap.add_argument("--headdim", type=int, default=64)
    ap.add_argument("--d-state", type=int, default=256)
    ap.add_argument("--ngroups", type=int, default=1)
    ap.add_argument("--chunk", type=int, default=256, help="chunk size of the chunked and dense forms")
    ap.add_argument(
        "--fused-chunk", type=int, default=128, help="chunk size of the fused form (128 measured fastest on CPU)"
    )
    ap.add_argument("--batch", type=int, default=1)
    ap.add_argument("--dtype", choices=["float32", "bfloat16"], default="float32")
    ap.add_argument("--repeats", type=int, help="override the preset's timed repeats")
    ap.add_argument("--mem-limit-gb", type=float, help="override the preset's activation budget")
    ap.add_argument("--no-backward", action="store_true", help="forward only")
    ap.add_argument(
        "--sequential-slice",
        type=int,
        default=4096,
        help="time the sequential forward on this many tokens when L is longer and scale "
        "linearly by L / slice (its per-step cost does not depend on L)",
    )
    args = ap.parse_args()

    preset = PRESETS[args.preset]
    lengths = args.lengths or preset["lengths"]
    repeats = args.repeats or preset["repeats"]
    mem_limit = (args.mem_limit_gb or preset["mem_limit_gb"]) * 2**30
    dtype = jnp.dtype(args.dtype)
    d_inner = args.expand * args.d_model
    nh, P, g, n = d_inner // args.headdim, args.headdim, args.ngroups, args.d_state
    Q, b = args.chunk, args.batch

    # Timings interleave: per L every job is compiled first, then each of `repeats` rounds
    # runs the matmul reference and every job once, so on a shared, busy machine the ratios
    # compare runs made under the same load (min over rounds is reported with the median).
    ka, kb = jax.random.split(jax.random.key(1))
    mm_n = preset["matmul_n"]
    mm_args = (jax.random.normal(ka, (mm_n, mm_n), dtype), jax.random.normal(kb, (mm_n, mm_n), dtype))
    mm = jax.jit(lambda a, b_: a @ b_).lower(*mm_args).compile()
    results, matmul_by_L = [], {}
    for L in lengths:
        x, dt, A, B, C, D = _inputs(L, b, nh, P, g, n, dtype)
        w = jnp.asarray(np.random.default_rng(1).standard_normal(x.shape), dtype)
        jobs = []  # (row, compiled, args, time scale)
        for method in args.methods:
            q = args.fused_chunk if method == "fused" else Q
            fwd = functools.partial(METHODS[method], Q=q)

            def loss(x, dt, A, B, C, D, w, fwd=fwd):
                return jnp.sum(fwd(x, dt, A, B, C, D).astype(jnp.float32) * w.astype(jnp.float32))

            # the cotangent w is an argument, not a closed-over constant (XLA would fold it)
            passes = [("fwd", fwd, (x, dt, A, B, C, D))]
            if not args.no_backward:
                passes.append(("fwd+bwd", jax.grad(loss, argnums=(0, 1, 2, 3, 4)), (x, dt, A, B, C, D, w)))  # pyright: ignore[reportArgumentType] -- a pass's arguments: any length
            for name, fn, fn_args in passes:
                row = {"L": L, "method": method, "pass": name, "chunk_size": q}
                if method == "fused":  # which loop the fused form runs (nn/ssd.py, _FACTOR_SPAN)
                    row["widest_chunk_span_nats"] = _widest_span(dt, A, q)
                    row["every_chunk_factorised"] = row["widest_chunk_span_nats"] <= ssd._FACTOR_SPAN
                results.append(row)
                need = _activation_bytes(method, name == "fwd+bwd", L, b, nh, P, g, n, q)
                scale = 1.0
                if method == "sequential" and name == "fwd" and L > args.sequential_slice:
                    m = args.sequential_slice
                    fn_args = tuple(a[:, :m] if a.ndim > 1 else a for a in fn_args)
                    row["extrapolated_from_L"], scale = m, L / m
                elif need > mem_limit:
                    row["skipped"] = f"predicted activations {need / 2**30:.1f} GiB > limit {mem_limit / 2**30:.1f} GiB"
                    print(f"L={L:6d} {method:20s} {name:8s} skipped: {row['skipped']}", flush=True)
                    continue
                try:
                    t0 = time.perf_counter()
                    compiled = jax.jit(fn).lower(*fn_args).compile()
                    row["compile_seconds"] = time.perf_counter() - t0
                    jax.block_until_ready(compiled(*fn_args))  # warm-up
                    jobs.append((row, compiled, fn_args, scale))
                except Exception as e:  # noqa: BLE001 - out-of-memory etc. are recorded, not fatal
                    row["skipped"] = f"{type(e).__name__}: {str(e).splitlines()[0][:200]}"
        times = {id(j[0]): [] for j in jobs}
        mm_times = []
        jax.block_until_ready(mm(*mm_args))
        for _ in range(repeats):
            t0 = time.perf_counter()
            jax.block_until_ready(mm(*mm_args))
            mm_times.append(time.perf_counter() - t0)
            for row, compiled, fn_args, scale in jobs:
                t0 = time.perf_counter()
                jax.block_until_ready(compiled(*fn_args))
                times[id(row)].append((time.perf_counter() - t0) * scale)
        matmul = {"n": mm_n, "seconds_min": min(mm_times), "gflops": 2.0 * mm_n**3 / min(mm_times) / 1e9}
        matmul_by_L[L] = matmul
        print(f"L={L:6d} matmul {mm_n}^3 {args.dtype}: {matmul['gflops']:.1f} GFLOP/s", flush=True)
        for row, _, _, _ in jobs:
            ts = times[id(row)]
            row.update(seconds_median=statistics.median(ts), seconds_min=min(ts))
            gflop = (
                _flops(row["method"], L, b, nh, P, g, n, row["chunk_size"])
                * (3 if row["pass"] == "fwd+bwd" else 1)
                / 1e9
            )
            row["gflop"] = gflop
            row["gflops_achieved"] = gflop / row["seconds_min"]
            row["fraction_of_matmul"] = row["gflops_achieved"] / matmul["gflops"]
            print(
                f"L={L:6d} {row['method']:20s} {row['pass']:8s} {row['seconds_min'] * 1e3:10.1f} ms "
                f"{row['gflops_achieved']:8.1f} GFLOP/s = {row['fraction_of_matmul']:.2f} x matmul "
                f"(compile {row['compile_seconds']:.1f} s)",
                flush=True,
            )
        del x, dt, B, C, w

    def seconds(L, method, name):
        rows = [r for r in results if (r["L"], r["method"], r["pass"]) == (L, method, name)]
        return rows[0].get("seconds_min") if rows else None

    def fraction(L, method, name):
        rows = [r for r in results if (r["L"], r["method"], r["pass"]) == (L, method, name)]
        return rows[0].get("fraction_of_matmul") if rows else None

    summary = []
    for L in lengths:
        seq = seconds(L, "sequential", "fwd")
        row = {"L": L}
        for method in ("chunked", "fused"):
            t = seconds(L, method, "fwd")
            row[f"sequential_over_{method}_fwd"] = seq / t if seq and t else None
            row[f"{method}_fraction_of_matmul_fwd"] = fraction(L, method, "fwd")
            row[f"{method}_fraction_of_matmul_fwd_bwd"] = fraction(L, method, "fwd+bwd")
        summary.append(row)
        print(json.dumps(summary[-1]), flush=True)
    report = {
        "benchmark": "ssd_scan",
        "device": str(jax.devices()[0]),
        "platform": jax.default_backend(),
        "device_count": jax.device_count(),
        "host": platform.processor() or platform.machine(),
        "cpu_count": os.cpu_count(),
        "load_average_1min_at_end": os.getloadavg()[0],  # shared boxes make timings noisy
        "jax_version": jax.__version__,
        "xla_flags": os.environ.get("XLA_FLAGS", ""),
        "preset": args.preset,
        "sizes": {
            "d_model": args.d_model,
            "d_inner": d_inner,
            "nheads": nh,
            "headdim": P,
            "d_state": n,
            "ngroups": g,
            "chunk_size": Q,
            "fused_chunk_size": args.fused_chunk,
            "batch": b,
            "dtype": args.dtype,
        },
        "repeats": repeats,
        "matmul_reference_by_L": matmul_by_L,
        "flop_model": "matmul FLOPs only (see bench_scan.py docstring); fwd+bwd = 3x fwd",
        "results": results,
        "summary": summary,
    }
    os.makedirs(os.path.dirname(os.path.abspath(args.out)), exist_ok=True)
    with open(args.out, "w") as f:
        json.dump(report, f, indent=2)
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
