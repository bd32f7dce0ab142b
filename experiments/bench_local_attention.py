"""Memory of the decoder's local (k-NN) attention: XLA temp bytes of one forward+backward.

    python experiments/bench_local_attention.py          # compile only, ~1 minute on 2 cores

For token grids of the paper's decoder (one target image: 256x256 -> 32x32 tokens,
960x544 -> 68x120, and 1920x1088 -> 136x240), k = 64 neighbours, E = 256 (4 heads of 64),
float32, one image: ``jit(grad).lower().compile().memory_analysis()`` of
``sum(local_attention(q, k, v) ** 2)`` w.r.t. q, k, v and the bias, next to the size of one
whole-neighbourhood gather ``[L, k, E]`` (what gathering K and V at once would hold, twice,
plus the copies kept for the backward pass). Nothing is run, so the numbers do not depend
on the machine's load; they are XLA's CPU plan (a GPU plan differs in detail, not in order).
Writes ``experiments/results/bench_local_attention.json``.
"""

from __future__ import annotations

import argparse
import json
import os
import platform

import jax
import jax.numpy as jnp

from llrmpp_jax.nn.local_attention import local_attention, neighbour_table

GRIDS = [(32, 32), (68, 120), (136, 240)]


def temp_bytes(h: int, w: int, k: int, nh: int, hd: int) -> int:
    index, _, _ = neighbour_table(h, w, k)
    qkv = jax.ShapeDtypeStruct((h * w, nh, hd), jnp.float32)
    bias = jax.ShapeDtypeStruct((h * w, min(k, h * w), nh), jnp.float32)

    def step(q, kk, v, b):
        loss = lambda *a: jnp.sum(local_attention(*a[:3], jnp.asarray(index), a[3]) ** 2)  # noqa: E731  # pyright: ignore[reportCallIssue] -- the unpacked tuple holds the other arguments
        return jax.grad(loss, argnums=(0, 1, 2, 3))(q, kk, v, b)

    return int(jax.jit(step).lower(qkv, qkv, qkv, bias).compile().memory_analysis().temp_size_in_bytes)  # pyright: ignore[reportOptionalMemberAccess] -- memory_analysis() is None only on a backend without it; CPU, GPU and TPU have it


def main() -> None:
    ap = argparse.ArgumentParser(description=(__doc__ or "").splitlines()[0])
    ap.add_argument("--k", type=int, default=64, help="neighbours per token")
    ap.add_argument("--heads", type=int, default=4, help="attention heads")
    ap.add_argument("--head-dim", type=int, default=64, help="channels per head")
    ap.add_argument(
        "--out", default=os.path.join("experiments", "results", "bench_local_attention.json"), help="JSON output path"
    )
    args = ap.parse_args()
    rows = []
    for h, w in GRIDS:
        t = temp_bytes(h, w, args.k, args.heads, args.head_dim)
        gather = h * w * args.k * args.heads * args.head_dim * 4
        rows.append(
            {
                "grid": [h, w],
                "tokens": h * w,
                "temp_bytes": t,
                "one_full_gather_bytes": gather,
                "temp_over_full_gather": t / gather,
            }
        )
        print(f"{h}x{w}: temp {t / 1e6:.1f} MB, one [L, k, E] gather {gather / 1e6:.1f} MB")
    os.makedirs(os.path.dirname(args.out), exist_ok=True)
    with open(args.out, "w") as f:
        json.dump(
            {
                "k": args.k,
                "heads": args.heads,
                "head_dim": args.head_dim,
                "dtype": "float32",
                "backend": jax.default_backend(),
                "jax": jax.__version__,
                "platform": platform.platform(),
                "rows": rows,
            },
            f,
            indent=1,
        )


if __name__ == "__main__":
    main()
