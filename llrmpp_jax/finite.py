"""Non-finite values refused where data enters: a NaN or an infinity in Gaussians read from
a file, in a capture's cameras or in a decoded image is one line naming the file, the field
and how many values are bad, before anything is computed from it."""

from __future__ import annotations

from collections.abc import Mapping

import numpy as np
from numpy.typing import ArrayLike

from llrmpp_jax.errors import UserError


def count_non_finite(values: ArrayLike) -> int:
    """How many entries of ``values`` are NaN or +-inf (0 for integer and boolean arrays)."""
    a = np.asarray(values)
    if a.dtype.kind not in "fc":
        return 0
    return int(a.size - np.count_nonzero(np.isfinite(a)))


def check_finite(source: str, fields: Mapping[str, ArrayLike], what: str = "") -> None:
    """``UserError`` naming ``source``, the first of ``fields`` that holds a NaN or an
    infinity and how many of its values do (with how many other fields do too); ``what``
    (e.g. ``"Gaussian field "``) precedes the field's name in the message."""
    bad = {name: (n, np.size(a)) for name, a in fields.items() if (n := count_non_finite(a))}
    if not bad:
        return
    name, (n, size) = next(iter(bad.items()))
    others = f" (and {len(bad) - 1} more field(s))" if len(bad) > 1 else ""
    raise UserError(f"{source}: {what}{name} has {n:,} non-finite value(s) (NaN or inf) of {size:,}{others}")
