"""One table of every executed ablation: each paper ordering, the paper's difference, ours.

Run:  python notebooks/_summary.py [--scale cpu]
      (reads experiments/results/ablations/table*_{scale}.json, prints Markdown)

The JSON records are the ones the notebooks write (:func:`llrmpp_jax.ablation.save`); a table that has
not been executed at the scale is listed as such, so the summary never hides a missing run.
Then the paper's central claims (:data:`CENTRAL`), each with the spread of its paired
differences and the seeds that would resolve the paper's difference and ours at that spread
(:func:`llrmpp_jax.ablation.seeds_to_resolve`). ``notebooks/README.md`` carries this output
under "Verdicts".
"""

from __future__ import annotations

import argparse
import json
import os
import re

import numpy as np
from _execute import notebook_names  # this folder: on sys.path when run as a script

from llrmpp_jax import ablation as A

# The paper's central claims, as (notebook, ordering over that notebook's rows). Computed from
# the per-seed scores in the notebook's JSON with the table's own interval level, so a claim
# that a notebook does not list as an ordering (Table 5's LLGGG > GGG) is scored the same way.
CENTRAL = [
    ("table5_decoder", A.Ordering("feature (LLGGG) > colour", 4, 0)),
    ("table6_partitions", A.Ordering("S=2 > S=1", 1, 0)),
    ("table4_feature_splat", A.Ordering("K16 F32 > K32 F16", 3, 6)),
    ("table5_decoder", A.Ordering("LLGGG > GGG", 4, 1)),
]

RESULTS = os.path.join(
    os.path.dirname(os.path.dirname(os.path.abspath(__file__))), "experiments", "results", "ablations"
)


def summary(scale: str = "cpu", folder: str = RESULTS) -> str:
    """Markdown: a line per executed table (wall time, commit, seeds, steps), then one table
    with every ordering of every executed table: the paper's difference, our paired
    difference with its interval (95% for fixed seeds, 99% for sequential tables), the seeds
    paired, and the verdict with what stopped a sequential ordering
    (:func:`llrmpp_jax.ablation.compare`)."""
    runs, missing = [], []
    for name in notebook_names():
        path = os.path.join(folder, f"{name}_{scale}.json")
        if os.path.isfile(path):
            with open(path) as f:
                runs.append((name, json.load(f)))
        else:
            missing.append(name)

    def seeds(r: dict) -> str:
        most = max((c.get("seeds", r["seeds"]) for c in r["orderings"]), default=r["seeds"])
        return f"{r['seeds']} seeds" if most == r["seeds"] else f"{r['seeds']} to {most} seeds (sequential)"

    lines = [
        f"- `{name}`: {r['wall_s'] / 60:.1f} min, {seeds(r)} x {r['steps']} steps, commit {r['commit']}"
        for name, r in runs
    ]
    lines += [f"- `{name}`: not executed at the {scale} scale" for name in missing]
    lines += [
        "",
        "| table | paper ordering | metric | paper diff | our diff (± interval) | level | seeds | verdict |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for name, r in runs:
        number = re.match(r"table(\d+)", name).group(1)
        for c in r["orderings"]:
            paper, ours = A.ordering_cells(c)
            level = f"{100 * c.get('confidence', 0.95):g}%"
            count = c.get("seeds", r["seeds"])
            stopped = f", stopped by {c['stopped']}" if "stopped" in c else ""
            lines.append(
                f"| {number} | {c['ordering']} | {c['metric']} | {paper} | {ours} | {level} | {count} | "
                f"{c['verdict']}{stopped} |"
            )
    return "\n".join(lines + ["", central(dict(runs))])


def central(runs: dict[str, dict]) -> str:
    """Markdown table of :data:`CENTRAL`: each claim's paired difference over the seeds both
    rows ran, its interval at the table's level, the verdict, the paired standard deviation
    and the seeds at which that spread resolves the paper's difference and ours (median
    case; "-" where the table has not run or a row has fewer than 2 seeds)."""
    lines = [
        "| table | central claim | paper diff | our diff (± interval) | level | seeds | verdict | "
        "paired std | seeds to resolve the paper's diff | seeds to resolve ours |",
        "|---|---|---|---|---|---|---|---|---|---|",
    ]
    for name, ordering in CENTRAL:
        number = re.match(r"table(\d+)", name).group(1)
        r = runs.get(name)
        if r is None:
            lines.append(f"| {number} | {ordering.text} | | | | | not executed | | | |")
            continue
        level = max((o.get("confidence", 0.95) for o in r["orderings"]), default=0.95)
        c = A.compare(r["results"], [ordering], level)[0]
        paper, ours = A.ordering_cells(c)
        if c["verdict"] == "not run" or c["seeds"] < 2:
            lines.append(f"| {number} | {ordering.text} | {paper} | {ours} | | | {c['verdict']} | | | |")
            continue
        sd = float(np.std(c["diff_seeds"], ddof=1))
        need = [
            A.seeds_to_resolve(sd, e, level, cap=1000) if e is not None else None for e in (c["paper_diff"], c["diff"])
        ]
        need_cells = [str(n) if n is not None else "over 1,000" for n in need]
        lines.append(
            f"| {number} | {ordering.text} | {paper} | {ours} | {100 * level:g}% | {c['seeds']} | "
            f"{c['verdict']} | {sd:.3f} | {need_cells[0]} | {need_cells[1]} |"
        )
    return "\n".join(lines)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--scale", default="cpu", choices=A.SCALES, help="the scale whose results to read")
    parser.add_argument("--folder", default=RESULTS, help="where the notebooks wrote their JSON")
    args = parser.parse_args()
    print(summary(args.scale, args.folder))


if __name__ == "__main__":
    main()
