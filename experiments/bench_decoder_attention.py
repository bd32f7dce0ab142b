"""The shipped small model's decoder on this CPU at a refinement step's shape: this tree
against a baseline commit, alternating rounds, each in a fresh process.

Run (the committed table, docs/speed-cpu.md "The decoder's attention"):

  python experiments/bench_decoder_attention.py --baseline 3b68f44 --rounds 2 \\
      --out experiments/results/bench_decoder_attention.json

Shapes: ``pretrained:small``'s decoder (``LG`` blocks, E = 128, 8 heads of 16, S = 2) on
8 target views of 256x192 (what ``llrmpp refine`` fits per step at its default of 8 views:
16 canvases of 128x96, 3,072 tokens each), with the shipped weights; and its global
attention alone (``multi_head_attention`` on ``[16, 3072, 8, 16]`` with the config's
blockwise kernel and blocks). Each number is the best of ``--repeats`` synced runs after
the compile, then the best over rounds: forward, and the gradient (forward + backward) of
a sum of squares of the output.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys

from git_worktree import REPO, rev_parse, worktree

CHILD = r"""
import json, sys, time
import jax, jax.numpy as jnp
from llrmpp_jax.decoder import TargetDecoder
from llrmpp_jax.nn.attention import multi_head_attention
from llrmpp_jax.pretrained import load_pretrained

repeats = int(sys.argv[1])

def best(fn, *args):
    jax.block_until_ready(fn(*args))
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        jax.block_until_ready(fn(*args))
        times.append(time.perf_counter() - start)
    return min(times)

params, cfg = load_pretrained("small")
d = cfg.decoder
m, h, w = 8, 256, 192
canvas = jax.random.normal(jax.random.key(0), (m, d.partitions, h // d.canvas_ratio, w // d.canvas_ratio,
                                                cfg.head.feature_dim + 6))
decoder = TargetDecoder(d)
variables = {"params": params["decoder"]}
forward = jax.jit(lambda p, x: decoder.apply(p, x)["rgb"])
gradient = jax.jit(jax.grad(lambda p, x: jnp.sum(decoder.apply(p, x)["rgb"] ** 2), argnums=(0, 1)))
rows = {"decoder": {"fwd_s": best(forward, variables, canvas), "fwd_bwd_s": best(gradient, variables, canvas)}}

t = d.transformer
shape = (m * d.partitions, (h // d.token_stride) * (w // d.token_stride), d.dim // t.head_dim, t.head_dim)
q, k, v = (jax.random.normal(key, shape) for key in jax.random.split(jax.random.key(1), 3))
attend = lambda q, k, v: multi_head_attention(q, k, v, block_q=t.attention_block_q, block_k=t.attention_block_k)
forward = jax.jit(attend)
gradient = jax.jit(jax.grad(lambda q, k, v: jnp.sum(attend(q, k, v) ** 2), argnums=(0, 1, 2)))
rows["global attention"] = {"shape": list(shape), "fwd_s": best(forward, q, k, v),
                            "fwd_bwd_s": best(gradient, q, k, v)}
print(json.dumps(rows))
"""


def measure(tree: str, repeats: int) -> dict:
    """One fresh process on the package in ``tree``: its rows."""
    out = subprocess.run(
        [sys.executable, "-c", CHILD, str(repeats)],
        check=True,
        capture_output=True,
        text=True,
        env=dict(os.environ, PYTHONPATH=tree),
        cwd=tree,
    )
    return json.loads(out.stdout.strip().splitlines()[-1])


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--baseline", required=True, metavar="REF", help="git commit to compare with")
    parser.add_argument("--rounds", type=int, default=2, help="alternating rounds (baseline, then this tree)")
    parser.add_argument("--repeats", type=int, default=3, help="timed runs per program (the best is kept)")
    parser.add_argument("--out", default=None, help="JSON path")
    args = parser.parse_args()
    runs: dict[str, list[dict]] = {"baseline": [], "this tree": []}
    with worktree(args.baseline) as tree:
        for r in range(args.rounds):
            for name, where in (("baseline", tree), ("this tree", REPO)):
                runs[name].append(measure(where, args.repeats))
                print(r, name, json.dumps(runs[name][-1]), flush=True)
    best = {}
    for row in runs["baseline"][0]:
        for key in ("fwd_s", "fwd_bwd_s"):
            before = min(run[row][key] for run in runs["baseline"])
            after = min(run[row][key] for run in runs["this tree"])
            best[f"{row} {key}"] = {"baseline": before, "this tree": after, "speedup": before / after}
    result = {
        "baseline": args.baseline,
        "commit": rev_parse("HEAD"),
        "cpu_count": os.cpu_count(),
        "runs": runs,
        "best_of_rounds": best,
    }
    print(json.dumps(best, indent=1))
    if args.out:
        with open(args.out, "w") as fh:
            json.dump(result, fh, indent=1)


if __name__ == "__main__":
    main()
