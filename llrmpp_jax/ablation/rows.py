"""A table's rows and the paper's claims about them: :class:`Variant` (a row),
:class:`Ordering` (row ``better`` beats row ``worse`` on a metric), :func:`selected`
(the rows ``LLRMPP_NOTEBOOK_ROWS`` asks for)."""

from __future__ import annotations

import os
from collections.abc import Callable, Sequence
from dataclasses import dataclass

from llrmpp_jax import config as C

# Scores a row is compared on, and whether higher is better.
METRICS = {"psnr": True, "ssim": True, "lpips": False, "abs_diff": False, "delta_1_25": True}


@dataclass(frozen=True)
class Variant:
    """One row of an ablation table.

    ``labels``: the row's label columns as the paper prints them. ``build``: base config ->
    the row's config (``None``: the row cannot be reproduced here; ``note`` says why).
    ``paper``: the paper's reported numbers for the row (strings as printed, "-" = none).
    ``grad_weight`` / ``normal_weight``: the depth loss's auxiliary weights (Table 7).
    """

    labels: dict[str, str]
    build: Callable[[C.ModelConfig], C.ModelConfig] | None
    paper: dict[str, str]
    chosen: bool = False
    grad_weight: float = 0.1
    normal_weight: float = 0.1
    note: str = ""


@dataclass(frozen=True)
class Ordering:
    """A claim of the paper: row ``better`` beats row ``worse`` on ``metric`` (a key of
    :data:`METRICS`; "beats" = higher, or lower for LPIPS and Abs Diff). ``text`` names it."""

    text: str
    better: int
    worse: int
    metric: str = "psnr"

    def __post_init__(self) -> None:
        if self.metric not in METRICS:
            raise ValueError(f"Ordering {self.text!r}: metric must be one of {sorted(METRICS)}, got {self.metric!r}")


def selected(variants: Sequence[Variant]) -> list[tuple[int, Variant]]:
    """``(index, variant)`` of the rows to run: all, or those in ``LLRMPP_NOTEBOOK_ROWS``."""
    rows = os.environ.get("LLRMPP_NOTEBOOK_ROWS")
    if not rows:
        return list(enumerate(variants))
    if rows == "none":
        return []
    try:
        keep = [int(r) for r in rows.split(",")]
    except ValueError:
        raise ValueError(f"LLRMPP_NOTEBOOK_ROWS={rows!r}: expected comma-separated row indices or 'none'") from None
    bad = [r for r in keep if not 0 <= r < len(variants)]
    if bad:
        raise ValueError(f"LLRMPP_NOTEBOOK_ROWS={rows!r}: rows {bad} outside 0..{len(variants) - 1}")
    return [(i, variants[i]) for i in keep]
