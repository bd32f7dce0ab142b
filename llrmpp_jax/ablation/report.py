"""Showing and keeping a table: :func:`format_run` and :func:`format_orderings`
(Markdown next to the paper's numbers), :func:`plot`, :func:`save` (JSON and PNG with the
revision and machine)."""

from __future__ import annotations

import json
import os
import platform
from collections.abc import Sequence
from typing import Any

import jax
import numpy as np

from llrmpp_jax.ablation.tables import TableRun
from llrmpp_jax.tables import Column, format_table


def _row_record(r: dict[str, Any], label_keys: Sequence[str], columns: Sequence[Column]) -> dict[str, Any]:
    """A result as a record of :func:`format_run`'s table: ``*`` for the chosen row, its
    labels, the paper's numbers under the ``paper:NAME`` keys and, for a row that ran, its
    scores."""
    paper = {c.key: r["paper"].get(c.key[6:], "-") for c in columns if c.key.startswith("paper:")}
    scores = r if r["status"] == "ok" else {}
    return {**scores, **paper, "": "*" if r["chosen"] else "", **{k: str(r[k]) for k in label_keys}}


def _reference_record(ref: dict[str, Any], label_keys: Sequence[str], columns: Sequence[Column]) -> dict[str, Any]:
    """A reference (untrained row, baseline) as a record: its name under the first label,
    its own scores, blank elsewhere."""
    blank = {c.key: "" for c in columns if c.key.startswith("paper:") or c.key not in ref}
    return {**ref, **blank, "": "", **{k: "" for k in label_keys}, label_keys[0]: ref["name"]}


def format_run(run: TableRun, label_keys: Sequence[str], columns: Sequence[Column] = ()) -> str:
    """The run as a :func:`llrmpp_jax.tables.format_table`: one line per result, the label
    columns, then ``columns`` (``"paper:NAME"`` reads the paper's number); ``*`` marks the
    paper's chosen row; then the references (untrained, baselines); rows that did not run
    show their status, rows whose splat buffer overflowed say by how much; a last line gives
    the scale, seeds, wall time and :func:`revision`.
    ``±``: half-width of the 95% interval over seeds."""
    records = [_row_record(r, label_keys, columns) for r in run.results] + [
        _reference_record(ref, label_keys, columns) for ref in run.references
    ]
    table = format_table(records, [Column(""), *(Column(k) for k in label_keys), *columns])
    notes = [f"row {r['row']}: {r['status']}" for r in run.results if r["status"] != "ok"]
    # Splat capacity overflow (SplatConfig.max_intersections) loses Gaussians: say so by row.
    notes += [
        f"row {r['row']}: the splat buffer overflowed: {r['train_dropped'] / max(run.scale.steps, 1):,.0f} "
        f"intersections dropped per training step, {r['eval_dropped'] / run.scale.eval_scenes:,.0f} "
        "per held-out scene (mean over seeds)"
        for r in run.results
        if r["status"] == "ok" and (r["train_dropped"] > 0 or r["eval_dropped"] > 0)
    ]
    counts = sorted({r.get("seeds", run.scale.seeds) for r in run.results if r["status"] == "ok"}) or [run.scale.seeds]
    seeds = (
        f"{counts[0]} seed(s) per row"
        if len(counts) == 1
        else f"{counts[0]}-{counts[-1]} seeds per row (added while an ordering was unresolved)"
    )
    footer = (
        f"{run.scale.name} scale, {seeds}, {run.scale.steps} steps, "
        f"wall time {run.seconds / 60:.1f} min, commit {revision()}"
    )
    return "\n".join([table, ""] + notes + ([""] if notes else []) + [footer])


def ordering_cells(c: dict[str, Any]) -> tuple[str, str]:
    """The paper's difference and ours (mean paired difference over seeds ± the half-width
    of its interval)
    of one :func:`compare` entry, as printed ("-" where there is none)."""
    ours = (
        f"{c['diff']:+.3f} ± {c['diff_ci']:.3f}"
        if "diff" in c and np.isfinite(c["diff_ci"])
        else f"{c['diff']:+.3f}"
        if "diff" in c
        else "-"
    )
    paper = f"{c['paper_diff']:+.3f}" if c.get("paper_diff") is not None else "-"
    return paper, ours


def format_orderings(comparisons: Sequence[dict[str, Any]]) -> str:
    """A Markdown table of :func:`compare`'s verdicts: the paper's difference, ours
    (:func:`ordering_cells`; > 0 = the paper's ordering holds), the seeds paired and, for a
    :func:`run_table` result, what stopped them; a last line gives the interval's level."""
    records = [
        {
            "ordering": c["ordering"],
            "metric": c["metric"],
            "paper_diff": paper,
            "diff": ours,
            "seeds": c.get("seeds", "-"),
            "verdict": c["verdict"],
            "stopped": c.get("stopped", ""),
        }
        for c, (paper, ours) in zip(comparisons, map(ordering_cells, comparisons))
    ]
    columns = [
        Column("ordering", "paper ordering"),
        Column("metric"),
        Column("paper_diff", "paper diff"),
        Column("diff", "our diff (± interval)"),
        Column("seeds"),
        Column("verdict"),
    ]
    if any("stopped" in c for c in comparisons):
        columns.append(Column("stopped", "stopped by"))
    lines = [format_table(records, columns)]
    levels = sorted({c["confidence"] for c in comparisons if "confidence" in c})
    if levels:
        lines += [
            "",
            "Intervals: paired differences over seeds, Student-t, "
            + " / ".join(f"{100 * lv:g}%" for lv in levels)
            + " two-sided.",
        ]
    return "\n".join(lines)


def _row_name(r: dict[str, Any], label_keys: Sequence[str]) -> str:
    return " ".join(str(r[k]) for k in label_keys)


def plot(run: TableRun, label_keys: Sequence[str], metric: str = "psnr", title: str = ""):
    """A matplotlib figure: left, ``metric`` per row (mean and 95% interval over seeds, each
    seed a dot, the references as horizontal lines); right, each row's training loss (mean
    over seeds, 25-step moving average)."""
    import matplotlib.pyplot as plt

    fig, (ax, ax_loss) = plt.subplots(1, 2, figsize=(12, 4.2))
    ok = [r for r in run.results if r["status"] == "ok"]
    names = [_row_name(r, label_keys) + (" *" if r["chosen"] else "") for r in ok]
    for i, r in enumerate(ok):
        ci = r.get(f"{metric}_ci", float("nan"))
        ax.errorbar(i, r[metric], yerr=ci if np.isfinite(ci) else None, fmt="o", color="C0", capsize=4)
        ax.plot([i] * len(r[f"{metric}_seeds"]), r[f"{metric}_seeds"], ".", color="C0", alpha=0.4)
    for j, ref in enumerate(run.references):
        if metric in ref:
            ax.axhline(ref[metric], color=f"C{j + 1}", ls="--", lw=1, label=ref["name"])
    ax.set_xticks(range(len(ok)), names, rotation=30, ha="right")
    ax.set_ylabel(f"held-out {metric} (mean, 95% interval)")
    if ax.get_legend_handles_labels()[0]:
        ax.legend(fontsize=8)
    ax.set_title(title or "rows")
    window = 25
    for i, r in enumerate(ok):
        loss = np.asarray(run.curves[r["row"]])
        if len(loss) >= window:
            loss = np.convolve(loss, np.ones(window) / window, mode="valid")
        ax_loss.plot(np.arange(len(loss)) + 1, loss, label=names[i], color=f"C{i}")
    ax_loss.set_yscale("log")
    ax_loss.set_xlabel("step")
    ax_loss.set_ylabel("training loss (mean over seeds)")
    if ok:
        ax_loss.legend(fontsize=7)
    fig.tight_layout()
    return fig


def revision() -> str:
    """The code's revision as the runner passes it in ``LLRMPP_NOTEBOOK_REVISION``
    (``notebooks/_execute.py`` and the ``experiments/`` scripts set it from the checkout;
    a wheel has none), ``unknown`` without it."""
    return os.environ.get("LLRMPP_NOTEBOOK_REVISION") or "unknown"


def machine() -> str:
    """One line: CPU / accelerator, core count, JAX backend and version."""
    dev = jax.devices()[0]
    return (
        f"{platform.processor() or platform.machine()}, {os.cpu_count()} cores, "
        f"jax {jax.__version__} on {dev.platform} ({dev.device_kind})"
    )


def save(name: str, run: TableRun, comparisons: Sequence[dict[str, Any]], figure: Any = None) -> str:
    """Write ``{name}_{scale}.json`` (and ``.png`` for ``figure``) under
    ``LLRMPP_NOTEBOOK_OUT`` (default ``runs/ablations`` in the working directory; ``make
    notebooks`` sets the repository's results folder), print and return the JSON path."""
    out = os.environ.get("LLRMPP_NOTEBOOK_OUT") or os.path.join("runs", "ablations")
    os.makedirs(out, exist_ok=True)
    path = os.path.join(out, f"{name}_{run.scale.name}.json")
    record = {
        "table": name,
        "scale": str(run.scale),
        "scale_name": run.scale.name,
        "seeds": run.scale.seeds,
        "steps": run.scale.steps,
        "commit": revision(),
        "machine": machine(),
        "wall_s": run.seconds,
        "results": run.results,
        "references": run.references,
        "orderings": list(comparisons),
        "curves": {str(k): v for k, v in run.curves.items()},
    }
    with open(path, "w") as f:
        json.dump(record, f, indent=1, default=float)
    if figure is not None:
        figure.savefig(path[:-5] + ".png", dpi=100)
    print(f"saved {path}")
    return path
