"""Global attention memory and speed: plain XLA vs blockwise (FlashAttention-2 in JAX).

One attention forward+backward of ``[1, L, 12, 64]`` (the paper backbone's heads):
XLA's ``memory_analysis()`` temp bytes of the compiled program for both implementations
(compile only, so the plain path at 131k tokens -- 0.8 TB of logits -- is analysed, not
run), and the blockwise kernel's compile and run times (``block_until_ready``) at
``--run-lengths``; on a GPU the cuDNN kernel is analysed and timed beside them
(:func:`attention_benchmark`). ``llrmpp bench`` runs this with its scale's arguments.

Usage: ``python -m llrmpp_jax.benchmarks.attention [--lengths 8192 32768 131072]
[--run-lengths 4096 8192] [--block 512] [--heads 12] [--head-dim 64] [--dtype float32] [--out PATH]``.
The decoder's global blocks (paper: E = 256, 4 heads of 64, 8,160 tokens per target at
960x544): ``--heads 4 --lengths 8160 --run-lengths``.
"""

from __future__ import annotations

import argparse
import json
import os
import time

from llrmpp_jax.benchmarks.measure import environment, timed


def attention_fwd_bwd(implementation: str, block: int = 512):
    """``(q, k, v, cotangent) -> (dq, dk, dv)`` of one global attention (a training step's
    share of it): forward and backward through :func:`multi_head_attention`."""
    import jax

    from llrmpp_jax.nn.attention import multi_head_attention

    def step(q, k, v, cot):
        _, vjp = jax.vjp(
            lambda q, k, v: multi_head_attention(q, k, v, implementation=implementation, block_q=block, block_k=block),  # pyright: ignore[reportArgumentType] -- a str checked against the Literal's values at run time
            q,
            k,
            v,
        )
        return vjp(cot)

    return step


def _one_line(e: Exception) -> str:
    return f"{type(e).__name__}: {(str(e).splitlines() or [''])[0][:300]}"


def attention_benchmark(
    lengths=(8192, 32768, 131072),
    run_lengths=(4096, 8192),
    heads: int = 12,
    head_dim: int = 64,
    block: int = 512,
    dtype: str = "float32",
    repeats: int = 2,
) -> dict:
    """Memory of one attention fwd+bwd ``[1, L, heads, head_dim]`` (the paper backbone's
    12 x 64 heads), plain vs blockwise (and cuDNN on a GPU), from XLA's ``memory_analysis()``
    of the compiled program (compile only: nothing is allocated); then compile and run times
    of the memory-efficient kernels (blockwise; cuDNN on a GPU) at ``run_lengths``.
    ``temp_bytes`` is XLA's scratch on top of the arguments (q, k, v, cotangent) and outputs
    (dq, dk, dv). A kernel that cannot be compiled or run at a length gets ``{"failed": ...}``
    in its row (on a GPU, XLA's compile of the plain kernel allocates its [L, L] buffers to
    autotune: L^2 x 4 bytes per head, far beyond a GPU's memory at L = 131k) and the other
    rows go on."""
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
            row[impl] = {
                "temp_bytes": int(ma.temp_size_in_bytes),  # pyright: ignore[reportOptionalMemberAccess] -- memory_analysis() is None only on a backend without it; CPU, GPU and TPU have it
                "argument_bytes": int(ma.argument_size_in_bytes),  # pyright: ignore[reportOptionalMemberAccess] -- memory_analysis() is None only on a backend without it; CPU, GPU and TPU have it
                "output_bytes": int(ma.output_size_in_bytes),  # pyright: ignore[reportOptionalMemberAccess] -- memory_analysis() is None only on a backend without it; CPU, GPU and TPU have it
                "compile_s": time.perf_counter() - t0,
            }
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
    return {
        "heads": heads,
        "head_dim": head_dim,
        "block": block,
        "dtype": dtype,
        "memory": rows,
        "blockwise_temp_bytes_per_token": {r["L"]: r["blockwise"]["temp_bytes"] / r["L"] for r in ok},
        "runs": runs,
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=(__doc__ or "").split("\n")[0])
    ap.add_argument(
        "--lengths",
        type=int,
        nargs="+",
        default=[8192, 32768, 131072],
        help="sequence lengths of the memory analysis (compile only)",
    )
    ap.add_argument(
        "--run-lengths",
        type=int,
        nargs="*",
        default=[4096, 8192],
        help="sequence lengths at which the blockwise kernel is also run and timed",
    )
    ap.add_argument("--block", type=int, default=512, help="blockwise query and key block size")
    ap.add_argument("--heads", type=int, default=12, help="attention heads (paper backbone 12, decoder 4)")
    ap.add_argument("--head-dim", type=int, default=64, help="channels per head")
    ap.add_argument("--dtype", default="float32", choices=("float32", "bfloat16"), help="q, k, v dtype")
    ap.add_argument("--repeats", type=int, default=2, help="timed runs after one warm-up")
    ap.add_argument("--out", default=os.path.join("runs", "bench", "bench_attention.json"), help="JSON file written")
    args = ap.parse_args()
    env = environment()
    result = attention_benchmark(
        args.lengths,
        args.run_lengths,
        heads=args.heads,
        head_dim=args.head_dim,
        block=args.block,
        dtype=args.dtype,
        repeats=args.repeats,
    )
    result["environment"] = env
    result["load_average_at_end"] = list(os.getloadavg())
    os.makedirs(os.path.dirname(os.path.abspath(args.out)), exist_ok=True)
    with open(args.out, "w") as f:
        json.dump(result, f, indent=1)
    print(
        json.dumps(
            {
                r["L"]: {i: r[i].get("temp_bytes", r[i].get("failed")) for i in r if isinstance(r[i], dict)}
                for r in result["memory"]
            }
        )
    )


if __name__ == "__main__":
    main()
