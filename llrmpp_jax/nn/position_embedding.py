"""Absolute 2-D positional embedding of a token grid: fixed sines and cosines of the coordinates.

For the paper's Table 5 baseline, "global attention with absolute positional
embeddings" (decoder ``GGG``). The kind is the fixed 2-D sin-cos embedding of MAE /
ViT-style models, not a learned table, because the decoder runs at any canvas size (the
training resolution, 540p evaluation, any render size): a learned ``[h*w, E]`` table
exists for one grid only and would need resampling, while the sin-cos value of a token
is defined by its coordinates alone, at any grid size, with no parameters. It is added
to the tokens once, after the decoder's tokenizer.
"""

from __future__ import annotations

import functools

import numpy as np

from llrmpp_jax.array_typing import Float

MAX_PERIOD = 10000.0


@functools.lru_cache(maxsize=32)
def sincos_2d(h: int, w: int, dim: int) -> Float[np.ndarray, "L C"]:
    """``[h*w, dim]`` float32 embedding of a row-major ``h x w`` grid (NumPy, static, read-only).

    With ``f = dim / 4`` frequencies ``omega_i = MAX_PERIOD^(-i / f)``, ``i = 0 .. f-1``,
    token ``(y, x)`` (token units) gets ``[sin(y omega), cos(y omega), sin(x omega),
    cos(x omega)]``, each block ``f`` wide. ``dim`` must be a multiple of 4.
    """
    if h < 1 or w < 1 or dim < 4 or dim % 4:
        raise ValueError(f"sincos_2d: need h, w >= 1 and dim a positive multiple of 4, got h={h}, w={w}, dim={dim}")
    f = dim // 4
    omega = MAX_PERIOD ** (-np.arange(f, dtype=np.float64) / f)
    y, x = (a.reshape(-1, 1).astype(np.float64) for a in np.divmod(np.arange(h * w), w))
    emb = np.concatenate([np.sin(y * omega), np.cos(y * omega), np.sin(x * omega), np.cos(x * omega)], axis=1)
    emb = emb.astype(np.float32)
    emb.setflags(write=False)
    return emb
