"""llrmpp_jax.tables.format_table against tables written out by hand (the oracle)."""

import math

import numpy as np

from llrmpp_jax.tables import Column, format_table


def test_cells_widths_and_alignment():
    """Strings as they are, integers with thousands separators, floats scaled with the
    column's digits, a finite ``_ci`` companion as ``± half-width``, ``-`` for a missing key
    or None; numeric columns right-aligned, the others left."""
    records = [
        {"name": "a", "n": 1048576, "t": 0.01234, "psnr": 20.104, "psnr_ci": 0.3149},
        {"name": "longer name", "n": np.int64(7), "t": np.float32(0.5), "psnr": math.nan, "psnr_ci": math.nan},
        {"name": "c", "n": None, "psnr": 9.0},
    ]
    text = format_table(
        records, [Column("name"), Column("n", "count"), Column("t", "t ms", 1, 1000.0), Column("psnr", "PSNR", 2)]
    )
    assert text.splitlines() == [
        "| name        |     count |  t ms |         PSNR |",
        "|-------------|----------:|------:|-------------:|",
        "| a           | 1,048,576 |  12.3 | 20.10 ± 0.31 |",
        "| longer name |         7 | 500.0 |          nan |",
        "| c           |         - |     - |         9.00 |",
    ]


def test_blank_and_text_columns():
    """A column of text (or blank) is left-aligned; a title shorter than 3 characters gets a
    3-wide column, so its rule is still Markdown's ``---``."""
    text = format_table([{"": "*", "v": "-"}, {"": "", "v": "x"}], [Column(""), Column("v")])
    assert text.splitlines() == ["|     | v   |", "|-----|-----|", "| *   | -   |", "|     | x   |"]
