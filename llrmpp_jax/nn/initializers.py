"""Weight initialisers of the linear layers.

Long-LRM's ``_init_weights`` draws every Linear weight from N(0, 0.02) (``DENSE_INIT``).
The head and the decoder take their std from their configs (``init_std``), where ``None``
means LeCun normal, std = 1/sqrt(fan-in): the two agree near fan-in 2,500 and differ 8x at
the width of the tiny CPU models (64).
"""

from __future__ import annotations

import flax.linen as nn


def linear_init(std: float | None) -> nn.initializers.Initializer:
    """``normal(std)``, or LeCun normal (std = 1/sqrt(fan-in)) for ``None``."""
    return nn.initializers.lecun_normal() if std is None else nn.initializers.normal(stddev=std)


def parse_init_std(text: str) -> float | None:
    """Command-line form of ``init_std``: a number, or ``"lecun"`` for ``None``."""
    return None if text == "lecun" else float(text)


DENSE_INIT = linear_init(0.02)
