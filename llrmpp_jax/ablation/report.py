"""Showing and keeping a table: :func:`format_table` and :func:`format_orderings`
(Markdown next to the paper's numbers), :func:`plot`, :func:`save` (JSON and PNG with the
commit and machine)."""

from __future__ import annotations

import json
import os
import platform
import subprocess
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import jax
import numpy as np

from llrmpp_jax.ablation.tables import TableRun

def _fmt(x: Any, digits: int) -> str:
    if x is None:
        return "-"
    if isinstance(x, str):
        return x
    if isinstance(x, (int, np.integer)):
        return f"{int(x):,}"
    return f"{x:.{digits}f}" if np.isfinite(x) else "nan"


@dataclass(frozen=True)
class Column:
    """A column of :func:`format_table`: ``key`` in a result (``"paper:NAME"`` reads the
    paper's number), its ``title``, decimal ``digits`` and a ``scale`` factor (e.g. 1000
    for ms). A key with a ``_ci`` companion is printed as ``mean ± half-width``."""

    key: str
    title: str
    digits: int = 2
    scale: float = 1.0


def _cell(r: dict[str, Any], c: Column) -> str:
    if c.key.startswith("paper:"):
        return r["paper"].get(c.key[6:], "-")
    if r.get("status", "ok") != "ok":
        return "-"
    value = r.get(c.key)
    if isinstance(value, float):
        value = value * c.scale
    text = _fmt(value, c.digits)
    ci = r.get(f"{c.key}_ci")
    if isinstance(ci, float) and np.isfinite(ci):
        text += f" ± {_fmt(ci * c.scale, c.digits)}"
    return text


def format_table(run: TableRun, label_keys: Sequence[str], columns: Sequence[Column] = ()) -> str:
    """A Markdown table: one line per result, the label columns, then ``columns``; ``*``
    marks the paper's chosen row; then the references (untrained, baselines); rows that did
    not run show their status, rows whose splat buffer overflowed say by how much; a last
    line gives the scale, seeds, wall time and commit.
    ``±``: half-width of the 95% interval over seeds."""
    head = ["", *label_keys, *[c.title for c in columns]]
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for r in run.results:
        cells = ["*" if r["chosen"] else "", *[str(r[k]) for k in label_keys]]
        lines.append("| " + " | ".join(cells + [_cell(r, c) for c in columns]) + " |")
    for ref in run.references:
        cells = ["", ref["name"], *[""] * (len(label_keys) - 1)]
        own = [c for c in columns if not c.key.startswith("paper:")]
        lines.append("| " + " | ".join(cells + [_cell({"paper": {}, **ref}, c) if c in own and c.key in ref
                                                else "" for c in columns]) + " |")
    notes = [f"row {r['row']}: {r['status']}" for r in run.results if r["status"] != "ok"]
    # Splat capacity overflow (SplatConfig.max_intersections) loses Gaussians: say so by row.
    notes += [f"row {r['row']}: the splat buffer overflowed: {r['train_dropped'] / max(run.scale.steps, 1):,.0f} "
              f"intersections dropped per training step, {r['eval_dropped'] / run.scale.eval_scenes:,.0f} "
              "per held-out scene (mean over seeds)"
              for r in run.results if r["status"] == "ok" and (r["train_dropped"] > 0 or r["eval_dropped"] > 0)]
    counts = sorted({r.get("seeds", run.scale.seeds) for r in run.results if r["status"] == "ok"}) or [run.scale.seeds]
    seeds = (f"{counts[0]} seed(s) per row" if len(counts) == 1 else
             f"{counts[0]}-{counts[-1]} seeds per row (added while an ordering was unresolved)")
    footer = (f"{run.scale.name} scale, {seeds}, {run.scale.steps} steps, "
              f"wall time {run.seconds / 60:.1f} min, commit {commit()}")
    return "\n".join(lines + [""] + notes + ([""] if notes else []) + [footer])


def ordering_cells(c: dict[str, Any]) -> tuple[str, str]:
    """The paper's difference and ours (mean paired difference over seeds ± the half-width
    of its interval)
    of one :func:`compare` entry, as printed ("-" where there is none)."""
    ours = (f"{c['diff']:+.3f} ± {c['diff_ci']:.3f}" if "diff" in c and np.isfinite(c["diff_ci"])
            else f"{c['diff']:+.3f}" if "diff" in c else "-")
    paper = f"{c['paper_diff']:+.3f}" if c.get("paper_diff") is not None else "-"
    return paper, ours


def format_orderings(comparisons: Sequence[dict[str, Any]]) -> str:
    """A Markdown table of :func:`compare`'s verdicts: the paper's difference, ours
    (:func:`ordering_cells`; > 0 = the paper's ordering holds), the seeds paired and, for a
    :func:`run_table` result, what stopped them; a last line gives the interval's level."""
    stopped = any("stopped" in c for c in comparisons)
    lines = ["| paper ordering | metric | paper diff | our diff (± interval) | seeds | verdict |"
             + (" stopped by |" if stopped else ""), "|---|---|---|---|---|---|" + ("---|" if stopped else "")]
    for c in comparisons:
        paper, ours = ordering_cells(c)
        lines.append(f"| {c['ordering']} | {c['metric']} | {paper} | {ours} | {c.get('seeds', '-')} | {c['verdict']} |"
                     + (f" {c.get('stopped', '')} |" if stopped else ""))
    levels = sorted({c["confidence"] for c in comparisons if "confidence" in c})
    if levels:
        lines += ["", "Intervals: paired differences over seeds, Student-t, "
                  + " / ".join(f"{100 * lv:g}%" for lv in levels) + " two-sided."]
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


def commit() -> str:
    """The repository's short commit, with ``+dirty`` when tracked files differ from it."""
    def git(*args: str) -> str:
        return subprocess.run(["git", *args], capture_output=True, text=True).stdout.strip()  # the working directory's
    head = git("rev-parse", "--short", "HEAD") or "unknown"
    return head + ("+dirty" if git("status", "--porcelain", "--untracked-files=no") else "")


def machine() -> str:
    """One line: CPU / accelerator, core count, JAX backend and version."""
    dev = jax.devices()[0]
    return (f"{platform.processor() or platform.machine()}, {os.cpu_count()} cores, "
            f"jax {jax.__version__} on {dev.platform} ({dev.device_kind})")


def save(name: str, run: TableRun, comparisons: Sequence[dict[str, Any]], figure: Any = None) -> str:
    """Write ``{name}_{scale}.json`` (and ``.png`` for ``figure``) under
    ``LLRMPP_NOTEBOOK_OUT`` (default ``runs/ablations`` in the working directory; ``make
    notebooks`` sets the repository's results folder), print and return the JSON path."""
    out = os.environ.get("LLRMPP_NOTEBOOK_OUT") or os.path.join("runs", "ablations")
    os.makedirs(out, exist_ok=True)
    path = os.path.join(out, f"{name}_{run.scale.name}.json")
    record = {
        "table": name, "scale": str(run.scale), "scale_name": run.scale.name, "seeds": run.scale.seeds,
        "steps": run.scale.steps, "commit": commit(), "machine": machine(), "wall_s": run.seconds,
        "results": run.results, "references": run.references, "orderings": list(comparisons),
        "curves": {str(k): v for k, v in run.curves.items()},
    }
    with open(path, "w") as f:
        json.dump(record, f, indent=1, default=float)
    if figure is not None:
        figure.savefig(path[:-5] + ".png", dpi=100)
    print(f"saved {path}")
    return path
