"""One table of every executed ablation: each paper ordering, the paper's difference, ours.

Run:  python notebooks/_summary.py [--scale cpu]
      (reads experiments/results/ablations/table*_{scale}.json, prints Markdown)

The JSON records are the ones the notebooks write (:func:`llrmpp_jax.ablation.save`); a table that has
not been executed at the scale is listed as such, so the summary never hides a missing run.
``notebooks/README.md`` carries this output under "Verdicts".
"""

from __future__ import annotations

import argparse
import json
import os
import re

from _execute import notebook_names  # this folder: on sys.path when run as a script

from llrmpp_jax import ablation as A

RESULTS = os.path.join(os.path.dirname(os.path.dirname(os.path.abspath(__file__))), "experiments", "results", "ablations")


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

    lines = [f"- `{name}`: {r['wall_s'] / 60:.1f} min, {seeds(r)} x {r['steps']} steps, commit {r['commit']}"
             for name, r in runs]
    lines += [f"- `{name}`: not executed at the {scale} scale" for name in missing]
    lines += ["", "| table | paper ordering | metric | paper diff | our diff (± interval) | level | seeds | verdict |",
              "|---|---|---|---|---|---|---|---|"]
    for name, r in runs:
        number = re.match(r"table(\d+)", name).group(1)
        for c in r["orderings"]:
            paper, ours = A.ordering_cells(c)
            level = f"{100 * c.get('confidence', 0.95):g}%"
            count = c.get("seeds", r["seeds"])
            stopped = f", stopped by {c['stopped']}" if "stopped" in c else ""
            lines.append(f"| {number} | {c['ordering']} | {c['metric']} | {paper} | {ours} | {level} | {count} | "
                         f"{c['verdict']}{stopped} |")
    return "\n".join(lines)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--scale", default="cpu", choices=A.SCALES, help="the scale whose results to read")
    parser.add_argument("--folder", default=RESULTS, help="where the notebooks wrote their JSON")
    args = parser.parse_args()
    print(summary(args.scale, args.folder))


if __name__ == "__main__":
    main()
