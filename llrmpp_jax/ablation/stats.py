"""Statistics over seeds: :func:`interval` (mean, sd, Student-t 95% half-width),
:func:`summarise` (per metric, over seeds), :func:`compare` (paired differences and a
verdict per paper ordering), :func:`seeds_to_resolve` (a power estimate for an ordering
that is not resolved)."""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np
from scipy import stats

from llrmpp_jax.ablation.rows import METRICS, Ordering


def interval(values: Sequence[float] | np.ndarray, confidence: float = 0.95) -> dict[str, float]:
    """Mean, sample standard deviation and the half-width of the two-sided Student-t
    ``confidence`` interval of the mean (NaN for fewer than 2 values)."""
    x = np.asarray(values, np.float64)
    n = len(x)
    if n < 2:
        return {"mean": float(np.mean(x)) if n else float("nan"), "std": float("nan"), "ci": float("nan")}
    sd = float(np.std(x, ddof=1))
    return {
        "mean": float(np.mean(x)),
        "std": sd,
        "ci": float(stats.t.ppf(0.5 + confidence / 2, n - 1) * sd / np.sqrt(n)),
    }


def summarise(per_seed: Sequence[dict[str, float]]) -> dict[str, Any]:
    """Per-metric mean (under the metric's own key, so tables read as before), ``_std``,
    ``_ci`` and the per-seed ``_seeds`` list."""
    out: dict[str, Any] = {}
    for k in per_seed[0]:
        values = [d[k] for d in per_seed]
        iv = interval(values)
        out.update({k: iv["mean"], f"{k}_std": iv["std"], f"{k}_ci": iv["ci"], f"{k}_seeds": values})
    return out


def compare(
    results: Sequence[dict[str, Any]], orderings: Sequence[Ordering], confidence: float = 0.95
) -> list[dict[str, Any]]:
    """For each ordering, the paired per-seed difference ``better - worse`` over the seeds
    both rows ran (sign flipped for lower-is-better metrics, so > 0 means the paper's
    ordering holds) with its ``confidence`` interval, the number of ``seeds`` paired, and a
    verdict: ``reproduced`` (interval above 0), ``reversed`` (below 0), ``not resolved``
    (contains 0, or fewer than 2 seeds), ``not run`` (a row did not run)."""
    by_row = {r["row"]: r for r in results}
    out = []
    for o in orderings:
        a, b = by_row.get(o.better), by_row.get(o.worse)
        entry: dict[str, Any] = {"ordering": o.text, "better": o.better, "worse": o.worse, "metric": o.metric}
        if a is None or b is None or a["status"] != "ok" or b["status"] != "ok" or o.metric not in a:
            out.append({**entry, "verdict": "not run"})
            continue
        sign = 1.0 if METRICS[o.metric] else -1.0
        n = min(len(a[f"{o.metric}_seeds"]), len(b[f"{o.metric}_seeds"]))
        diffs = sign * (np.asarray(a[f"{o.metric}_seeds"][:n]) - np.asarray(b[f"{o.metric}_seeds"][:n]))
        iv = interval(diffs, confidence)
        paper = _paper_number(a, o.metric), _paper_number(b, o.metric)
        out.append(
            {
                **entry,
                "diff": iv["mean"],
                "diff_ci": iv["ci"],
                "confidence": confidence,
                "diff_seeds": diffs.tolist(),
                "seeds": n,
                "paper_diff": None if None in paper else sign * (paper[0] - paper[1]),  # pyright: ignore[reportOperatorIssue] -- None in paper is tested first
                "verdict": verdict(iv, n),
            }
        )
    return out


def seeds_to_resolve(diff_std: float, effect: float, confidence: float = 0.99, cap: int = 100_000) -> int | None:
    """Seeds at which a paired difference of mean ``effect`` and per-seed standard deviation
    ``diff_std`` has its two-sided Student-t ``confidence`` interval just exclude 0: the
    smallest n >= 2 with ``t_{(1 + confidence) / 2, n - 1} diff_std / sqrt(n) < |effect|``.

    A power estimate for an ordering that is not resolved: with ``diff_std`` the spread
    measured over the seeds run so far, about half of the tables whose true difference is
    ``effect`` resolve by then (the interval is centred on the observed mean); roughly twice
    as many seeds make it ~80% (1.96 + 0.84 = 2.8 standard errors instead of ~2). None when
    ``effect`` is 0 or more than ``cap`` seeds would be needed."""
    if effect == 0:
        return None
    if not diff_std > 0:
        return 2
    n = 2
    while n <= cap:
        if stats.t.ppf(0.5 + confidence / 2, n - 1) * diff_std / np.sqrt(n) < abs(effect):
            return n
        n += 1
    return None


def verdict(iv: dict[str, float], n: int) -> str:
    """``reproduced`` / ``reversed`` when the :func:`interval` ``iv`` of ``n`` paired
    differences lies above / below 0, else ``not resolved``."""
    if n < 2 or not abs(iv["mean"]) > iv["ci"]:
        return "not resolved"
    return "reproduced" if iv["mean"] > 0 else "reversed"


_PAPER_KEY = {"psnr": "PSNR", "ssim": "SSIM", "lpips": "LPIPS", "abs_diff": "Abs Diff", "delta_1_25": "delta<1.25"}


def _paper_number(row: dict[str, Any], metric: str) -> float | None:
    try:
        return float(row["paper"].get(_PAPER_KEY[metric], "-"))
    except ValueError:
        return None
