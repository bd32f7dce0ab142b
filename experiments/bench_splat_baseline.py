"""The splatter's speed against an older commit's, on the same machine in the same run.

Runs ``python -m llrmpp_jax.benchmarks.splat`` (the package's benchmark) on this tree and on
a temporary git worktree at ``--baseline`` (commits from before the benchmark moved into the
package run their ``experiments/bench_splat.py``), alternating ``--rounds`` times, each run
in a fresh process, then keeps each row's median time over the rounds and the speed-up per
(N, canvas) and capacity rule. The JSON is this tree's benchmark file (``rows``,
``exponents``) with ``baseline`` (the old commit's rows, ``ref`` its hash) and ``speedup``
added. Sweep options after ``--`` go to both runs; the baseline skips the oracle
(``--oracle-max-work 0``) and keeps its own default capacity rule.

The committed table (docs/speed-cpu.md, "The splatter"):

  python experiments/bench_splat_baseline.py --baseline 49415ad --rounds 2 \\
      --out experiments/results/splat_speed.json -- --n 100000 --canvas 128x128 256x256 --repeats 10
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile

from git_worktree import REPO, rev_parse, worktree

from llrmpp_jax.benchmarks.splat import fit_exponents, median_rows

# Where the benchmark lived at commits before it moved into the package (inside their worktree).
OLD_SCRIPT = os.path.join("experiments", "bench_splat.py")
# Options both versions of the benchmark take (the baseline gets these alone).
SHARED = ("--n", "--canvas", "--features", "--repeats", "--seed")


def run_sweep(tree: str, argv: list[str], out: str) -> dict:
    """One run of the splat benchmark of the checkout at ``tree`` in a fresh process; its JSON."""
    moved = os.path.exists(os.path.join(tree, "llrmpp_jax", "benchmarks", "splat.py"))
    entry = ["-m", "llrmpp_jax.benchmarks.splat"] if moved else [os.path.join(tree, OLD_SCRIPT)]
    subprocess.run(
        [sys.executable, *entry, *argv, "--out", out], check=True, cwd=tree, env=dict(os.environ, PYTHONPATH=tree)
    )
    with open(out) as fh:
        return json.load(fh)


def shared_options(argv: list[str]) -> list[str]:
    """The part of ``argv`` (``--opt value ...`` groups) whose options are in :data:`SHARED`."""
    out, keep = [], False
    for arg in argv:
        if arg.startswith("--"):
            keep = arg.split("=")[0] in SHARED
        if keep:
            out.append(arg)
    return out


def speedups(base_rows: list[dict], rows: list[dict]) -> list[dict]:
    """Baseline time / current time per (N, canvas) and capacity rule, forward and fwd+bwd."""
    base = {(r["n"], r["width"], r["height"]): r for r in base_rows}
    out = []
    for r in rows:
        b = base.get((r["n"], r["width"], r["height"]))
        if b is not None:
            out.append(
                {
                    "n": r["n"],
                    "canvas": f"{r['width']}x{r['height']}",
                    "capacity_rule": r["capacity_rule"],
                    "baseline_fwd_s": b["fwd_s"],
                    "fwd_s": r["fwd_s"],
                    "fwd_speedup": b["fwd_s"] / r["fwd_s"],
                    "baseline_fwd_bwd_s": b["fwd_bwd_s"],
                    "fwd_bwd_s": r["fwd_bwd_s"],
                    "fwd_bwd_speedup": b["fwd_bwd_s"] / r["fwd_bwd_s"],
                }
            )
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--baseline", required=True, metavar="REF", help="git commit to compare with")
    parser.add_argument("--rounds", type=int, default=2, help="alternating rounds (baseline, then this tree)")
    parser.add_argument("--out", required=True, help="JSON file to write")
    parser.add_argument("sweep", nargs=argparse.REMAINDER, help="-- then the benchmark's sweep options")
    args = parser.parse_args()
    sweep = args.sweep[1:] if args.sweep[:1] == ["--"] else args.sweep
    if args.rounds < 1:
        parser.error(f"--rounds must be >= 1, got {args.rounds}")
    base_argv = [*shared_options(sweep), "--oracle-max-work", "0"]
    runs: dict[str, list[dict]] = {"baseline": [], "this tree": []}
    with tempfile.TemporaryDirectory() as tmp, worktree(args.baseline) as tree:
        for r in range(args.rounds):
            runs["baseline"].append(run_sweep(tree, base_argv, os.path.join(tmp, f"baseline_{r}.json")))
            runs["this tree"].append(run_sweep(REPO, sweep, os.path.join(tmp, f"this_{r}.json")))
    rows = median_rows([run["rows"] for run in runs["this tree"]])
    base_rows = median_rows([run["rows"] for run in runs["baseline"]])
    result = runs["this tree"][0] | {
        "rows": rows,
        "rounds": args.rounds,
        "exponents": {"fwd_s": fit_exponents(rows, "fwd_s"), "fwd_bwd_s": fit_exponents(rows, "fwd_bwd_s")},
        "baseline": runs["baseline"][0] | {"rows": base_rows, "ref": rev_parse(args.baseline)},
        "speedup": speedups(base_rows, rows),
    }
    print(json.dumps(result["speedup"], indent=1))
    os.makedirs(os.path.dirname(os.path.abspath(args.out)), exist_ok=True)
    with open(args.out, "w") as fh:
        json.dump(result, fh, indent=1)
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
