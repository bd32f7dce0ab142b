"""Tables as text: :func:`format_table`, the one formatter of the package's tables (``llrmpp
eval``'s and the demo's summaries, the ablation notebooks' rows).

A table is a list of records (dicts) and its :class:`Column` s; the text is Markdown with
padded columns, so it reads in a terminal and pastes into ``docs/`` as it is.
"""

from __future__ import annotations

import math
import numbers
import re
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

# A number as printed ("1,024", "-0.25", "nan", "20.10 ± 0.31"): its column is right-aligned.
_NUMBER = re.compile(r"[-+]?(\d[\d,]*(\.\d*)?|nan|inf)( ± .*)?")


@dataclass(frozen=True)
class Column:
    """A column of :func:`format_table`: ``key`` in a record, its ``title`` (default: the
    key), decimal ``digits`` of a float and a ``scale`` factor for floats (e.g. 1000 for
    ms). A key with a finite ``{key}_ci`` companion in the record is printed as
    ``mean ± half-width``."""

    key: str
    title: str | None = None
    digits: int = 2
    scale: float = 1.0


def _text(value: Any, c: Column) -> str:
    """One value as text: ``-`` for None, a string as is, an integer with thousands
    separators, any other number scaled and with ``c.digits`` decimals (``nan``, ``inf`` as
    such)."""
    if value is None:
        return "-"
    if isinstance(value, str):
        return value
    if isinstance(value, numbers.Integral):
        return f"{int(value):,}"
    return f"{float(value) * c.scale:.{c.digits}f}"


def _cell(record: Mapping[str, Any], c: Column) -> str:
    text = _text(record.get(c.key), c)
    ci = record.get(f"{c.key}_ci")
    if isinstance(ci, numbers.Real) and math.isfinite(ci):
        text += f" ± {_text(ci, c)}"
    return text


def format_table(records: Sequence[Mapping[str, Any]], columns: Sequence[Column]) -> str:
    """A Markdown table: a header of the columns' titles, then one line per record with
    each column's value (:class:`Column`; ``-`` where the record has no such key). Columns
    are padded to their widest cell; a column of numbers (blank and ``-`` aside) is
    right-aligned (``---:``), the others left-aligned."""
    titles = [c.key if c.title is None else c.title for c in columns]
    cells = [[_cell(r, c) for c in columns] for r in records]
    widths = [max([3, len(t), *(len(row[j]) for row in cells)]) for j, t in enumerate(titles)]
    filled = [[row[j] for row in cells if row[j] not in ("", "-")] for j in range(len(columns))]
    right = [bool(texts) and all(_NUMBER.fullmatch(t) for t in texts) for texts in filled]

    def line(texts: Sequence[str]) -> str:
        return (
            "| "
            + " | ".join(t.rjust(w) if rj else t.ljust(w) for t, w, rj in zip(texts, widths, right, strict=True))
            + " |"
        )

    rule = "|" + "|".join("-" * (w + 1) + ":" if rj else "-" * (w + 2) for w, rj in zip(widths, right)) + "|"
    return "\n".join([line(titles), rule, *(line(row) for row in cells)])
