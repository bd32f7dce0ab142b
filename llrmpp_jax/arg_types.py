"""``argparse`` ``type=`` converters for the command line's numbers: an out-of-range,
non-finite or malformed value is refused by the parser (one ``error:`` line naming the flag,
exit status 2) before anything loads or compiles, so no such value reaches a jitted function.

Each converter takes the flag's text and returns the value; the bounds are stated in the
message (``argument --frames: must be an integer >= 1, got '0'``). The upper bounds are far
beyond any real use (a view side of 16,384 px, a million steps); they keep a typo such as
``--frames 10000000000`` from becoming hours of work or an allocation that cannot succeed.
"""

from __future__ import annotations

import argparse
import math
from collections.abc import Callable

MAX_SIDE = 16384  # px: a view or render side
MAX_COUNT = 1_000_000  # steps, frames, scenes, repeats


def _refuse(what: str, text: str) -> argparse.ArgumentTypeError:
    return argparse.ArgumentTypeError(f"must be {what}, got {text!r}")


def _number(v: float) -> str:
    return f"{v:,}" if isinstance(v, int) else f"{v:g}"


def _bounds(lo: float | None, hi: float | None) -> str:
    if lo is not None and hi is not None:
        return f"in [{_number(lo)}, {_number(hi)}]"
    return f">= {_number(lo)}" if lo is not None else f"<= {_number(hi)}"  # pyright: ignore[reportArgumentType] -- one of them is given


def int_in(lo: int | None = None, hi: int | None = None, *, also: int | None = None) -> Callable[[str], int]:
    """A converter to an ``int`` in ``[lo, hi]`` (either bound may be open), or exactly ``also``
    (e.g. ``-1`` for "all cores")."""
    what = "an integer " + _bounds(lo, hi) + (f" (or {also})" if also is not None else "")

    def convert(text: str) -> int:
        try:
            value = int(text.strip())
        except ValueError:  # also a number of more than 4300 digits (Python's limit)
            raise _refuse(what, text) from None
        if value == also:
            return value
        if (lo is not None and value < lo) or (hi is not None and value > hi):
            raise _refuse(what, text)
        return value

    convert.__name__ = "int"
    return convert


def float_in(lo: float | None = None, hi: float | None = None, *, above: bool = False) -> Callable[[str], float]:
    """A converter to a finite ``float`` in ``[lo, hi]`` (``above``: strictly greater than
    ``lo``); NaN and infinities are refused."""
    what = "a finite number " + (f"> {_number(lo)}" if above and lo is not None and hi is None else _bounds(lo, hi))

    def convert(text: str) -> float:
        try:
            value = float(text)
        except ValueError:
            raise _refuse(what, text) from None
        if not math.isfinite(value):
            raise _refuse(what, text)
        if lo is not None and (value < lo or (above and value == lo)):
            raise _refuse(what, text)
        if hi is not None and value > hi:
            raise _refuse(what, text)
        return value

    convert.__name__ = "float"
    return convert


positive_int = int_in(1, MAX_COUNT)
non_negative_int = int_in(0, MAX_COUNT)
seed = int_in(0, 2**31 - 1)
non_negative_float = float_in(0.0)
positive_float = float_in(0.0, above=True)


def _ints(text: str, sep: str) -> list[int] | None:
    try:
        return [int(v) for v in text.lower().split(sep)]
    except ValueError:
        return None


def view_size(text: str) -> tuple[int, int | None]:
    """``"H"`` -> ``(H, None)`` (the width keeps the capture's aspect), ``"HxW"`` -> ``(H, W)``;
    each side in ``[1, MAX_SIDE]``."""
    parts = _ints(text, "x")
    if parts is None or len(parts) not in (1, 2) or not all(1 <= v <= MAX_SIDE for v in parts):
        raise _refuse(f"H or HxW (e.g. 256 or 256x448), each side in [1, {MAX_SIDE}]", text)
    return parts[0], (parts[1] if len(parts) == 2 else None)


def height_width(text: str) -> tuple[int, int]:
    """``"HxW"`` -> ``(H, W)``, each side in ``[1, MAX_SIDE]``."""
    parts = _ints(text, "x")
    if parts is None or len(parts) != 2 or not all(1 <= v <= MAX_SIDE for v in parts):
        raise _refuse(f"HxW (e.g. 544x960), each side in [1, {MAX_SIDE}]", text)
    return parts[0], parts[1]


def frame_indices(text: str) -> tuple[int, ...]:
    """``"0,5,9"`` -> ``(0, 5, 9)``: one or more frame indices >= 0 (whether each is a frame
    of the capture is checked when the capture is read)."""
    parts = _ints(text, ",")
    if not parts or min(parts) < 0 or max(parts) > MAX_COUNT:
        raise _refuse("comma-separated frame indices >= 0 (e.g. 0,5,9)", text)
    return tuple(parts)


def view_counts(text: str) -> tuple[int, ...]:
    """``"16,32,64"`` -> ``(16, 32, 64)``: one or more view counts in ``[1, 4096]``."""
    parts = _ints(text, ",")
    if not parts or not all(1 <= v <= 4096 for v in parts):
        raise _refuse("comma-separated view counts in [1, 4096] (e.g. 16,32,64)", text)
    return tuple(parts)
