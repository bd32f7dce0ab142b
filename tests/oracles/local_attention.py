"""k-nearest-neighbour local attention by brute force, independent of the library: each
token's neighbours by sorting *every* grid token by (squared distance, dy, dx), their
relative-position features by formula, and the dense ``[L, L]`` mask and bias that restrict
``attention_module_oracle`` (``tests/oracles/attention.py``) to them. The tests of
``nn/local_attention.py`` and ``nn/transformer.py`` use them."""

import math

import numpy as np

from tests.oracles.attention import gelu


def brute_neighbours(h: int, w: int, k: int) -> list[list[tuple[int, int]]]:
    """Per token (row-major), the (dy, dx) of its min(k, h*w) nearest grid tokens, tie rule applied."""
    out = []
    for y in range(h):
        for x in range(w):
            offs = [(ty - y, tx - x) for ty in range(h) for tx in range(w)]
            out.append(sorted(offs, key=lambda o: (o[0] ** 2 + o[1] ** 2, o[0], o[1]))[:k])
    return out


def oracle_features(offsets) -> np.ndarray:
    rows = []
    for dy, dx in offsets:
        d = math.hypot(dx, dy)
        rows.append([0.0] * 5 if d == 0 else [dx, dy, d, dx / d, dy / d])
    return np.array(rows).reshape(-1, 5)


def dense_mask_bias(h: int, w: int, k: int, pair_bias: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Dense ``[L, L]`` neighbour mask and ``[nh, L, L]`` bias; ``pair_bias[l, j]`` belongs to
    token l's j-th nearest neighbour."""
    n = h * w
    mask = np.zeros((n, n), bool)
    bias = np.zeros((pair_bias.shape[-1], n, n))
    for t, offs in enumerate(brute_neighbours(h, w, k)):
        y, x = divmod(t, w)
        for j, (dy, dx) in enumerate(offs):
            mask[t, (y + dy) * w + x + dx] = True
            bias[:, t, (y + dy) * w + x + dx] = pair_bias[t, j]
    return mask, bias


def module_mask_bias(grid, k):
    """``mask_bias`` for ``attention_module_oracle``: the bias MLP on each pair's true offset."""

    def fn(p):
        rb = p["rel_bias"]
        offs = brute_neighbours(*grid, k)  # pyright: ignore[reportCallIssue] -- the unpacked tuple holds the other arguments
        feats = np.stack([oracle_features(o) for o in offs])  # [L, kn, 5]
        pair = gelu(feats @ rb["fc1"]["kernel"] + rb["fc1"]["bias"]) @ rb["fc2"]["kernel"]
        return dense_mask_bias(*grid, k, pair)  # pyright: ignore[reportCallIssue] -- the unpacked tuple holds the other arguments

    return fn
