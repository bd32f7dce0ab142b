"""The fixed 2-D sin-cos positional embedding, one token at a time from its formula."""

import math

import numpy as np


def sincos_2d_oracle(h: int, w: int, dim: int) -> np.ndarray:
    f = dim // 4
    rows = []
    for y in range(h):
        for x in range(w):
            om = [10000.0 ** (-i / f) for i in range(f)]
            rows.append(
                [math.sin(y * o) for o in om]
                + [math.cos(y * o) for o in om]
                + [math.sin(x * o) for o in om]
                + [math.cos(x * o) for o in om]
            )
    return np.array(rows)
