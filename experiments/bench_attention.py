"""Global attention memory and speed: plain XLA vs blockwise (FlashAttention-2 in JAX).

One attention forward+backward of ``[1, L, 12, 64]`` (the paper backbone's heads):
XLA's ``memory_analysis()`` temp bytes of the compiled program for both implementations
(compile only, so the plain path at 131k tokens -- 0.8 TB of logits -- is analysed, not
run), and the blockwise kernel's compile and run times (``block_until_ready``) at
``--run-lengths``; on a GPU the cuDNN kernel is analysed and timed beside them. See :func:`llrmpp_jax.bench.attention_benchmark`; ``llrmpp bench``
runs this with its scale's arguments.

Usage: ``python experiments/bench_attention.py [--lengths 8192 32768 131072]
[--run-lengths 4096 8192] [--block 512] [--heads 12] [--head-dim 64] [--dtype float32] [--out PATH]``.
The decoder's global blocks (paper: E = 256, 4 heads of 64, 8,160 tokens per target at
960x544): ``--heads 4 --lengths 8160 --run-lengths --out
experiments/results/bench_attention_decoder.json``.
"""

from __future__ import annotations

import argparse
import json
import os

from llrmpp_jax.bench import attention_benchmark
from llrmpp_jax.bench_measure import environment


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--lengths", type=int, nargs="+", default=[8192, 32768, 131072],
                    help="sequence lengths of the memory analysis (compile only)")
    ap.add_argument("--run-lengths", type=int, nargs="*", default=[4096, 8192],
                    help="sequence lengths at which the blockwise kernel is also run and timed")
    ap.add_argument("--block", type=int, default=512, help="blockwise query and key block size")
    ap.add_argument("--heads", type=int, default=12, help="attention heads (paper backbone 12, decoder 4)")
    ap.add_argument("--head-dim", type=int, default=64, help="channels per head")
    ap.add_argument("--dtype", default="float32", choices=("float32", "bfloat16"), help="q, k, v dtype")
    ap.add_argument("--repeats", type=int, default=2, help="timed runs after one warm-up")
    ap.add_argument("--out", default=os.path.join(os.path.dirname(__file__), "results", "bench_attention.json"))
    args = ap.parse_args()
    env = environment()
    result = attention_benchmark(args.lengths, args.run_lengths, heads=args.heads, head_dim=args.head_dim,
                                 block=args.block, dtype=args.dtype, repeats=args.repeats)
    result["environment"] = env
    result["load_average_at_end"] = list(os.getloadavg())
    with open(args.out, "w") as f:
        json.dump(result, f, indent=1)
    print(json.dumps({r["L"]: {i: r[i].get("temp_bytes", r[i].get("failed")) for i in r if isinstance(r[i], dict)}
                      for r in result["memory"]}))


if __name__ == "__main__":
    main()
