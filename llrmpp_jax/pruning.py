"""Long-LRM's Gaussian pruning (its stage 3 at 960x540) and the ``gaussian_usage`` statistic.

Long-LRM (``model/llrm.py``, facts §1.6) prunes the predicted colour Gaussians before
rendering, in training and in evaluation alike, when ``prune_ratio > 0`` (its
``dl3dv_i540`` config: ``prune_ratio=0.6``, ``random_ratio=0.1``). Its arithmetic, kept
here exactly (Python floats, truncation by ``int``) so the counts match at every N::

    keep = 1 - prune_ratio;  rand = keep * random_ratio;  keep = keep - rand
    num_top = int(N * keep);  num_random = int(N * rand)

The ``num_top`` most opaque Gaussians are kept, plus ``num_random`` drawn uniformly
without replacement from the rest; the draw is one permutation of the rest's rank
positions shared by every scene of the batch (``rest_idx[:, randperm(...)]`` upstream).
At 32 views of 960x544 that is 6,016,204 + 668,467 of 16,711,680 Gaussians.

Ranking: upstream argsorts the opacity *logits*; we sort the opacities (the sigmoid,
monotone in the logit, so the same order) with ties broken by index. The two can only
differ where float32's sigmoid saturates to 1 (logits above ~16.6) and more such
Gaussians exist than are kept.

``gaussian_usage`` (logged by upstream before pruning): the fraction of a scene's
Gaussians with opacity above 0.001.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

from llrmpp_jax.array_typing import Array, Float, KeyArray
from llrmpp_jax.gaussians import Gaussians

USAGE_THRESHOLD = 0.001


def gaussian_usage(opacities: Float[Array, "B N"]) -> Float[Array, " B"]:
    """Fraction of each scene's Gaussians with opacity ``> USAGE_THRESHOLD`` (float32)."""
    return jnp.mean(opacities > USAGE_THRESHOLD, axis=-1, dtype=jnp.float32)


def pruned_counts(n: int, prune_ratio: float, random_ratio: float) -> tuple[int, int]:
    """``(num_top, num_random)`` kept of ``n`` Gaussians, with Long-LRM's exact arithmetic."""
    keep = 1 - prune_ratio
    rand = keep * random_ratio
    keep = keep - rand
    return int(n * keep), int(n * rand)


def prune_gaussians(gaussians: Gaussians, prune_ratio: float, random_ratio: float, key: KeyArray) -> Gaussians:
    """Keep the most opaque Gaussians plus a random share of the rest (module docstring).

    ``gaussians`` has ``[B, N, ...]`` fields; the result has ``[B, num_top + num_random,
    ...]`` (static), the top ones first in decreasing opacity, then the random ones.
    ``prune_ratio == 0`` returns ``gaussians`` unchanged. ``key`` draws the random share.
    Differentiable in the kept Gaussians' values (gradients of pruned ones are 0).
    """
    if not 0 <= prune_ratio < 1 or not 0 <= random_ratio <= 1:
        raise ValueError(
            f"prune_gaussians: need 0 <= prune_ratio < 1 and 0 <= random_ratio <= 1, got "
            f"prune_ratio={prune_ratio}, random_ratio={random_ratio}"
        )
    if prune_ratio == 0:
        return gaussians
    b, n = gaussians.opacities.shape
    num_top, num_random = pruned_counts(n, prune_ratio, random_ratio)
    order = jnp.argsort(gaussians.opacities, axis=1, descending=True, stable=True)  # [B, N]
    keep = order[:, :num_top]
    if num_random:
        pick = jax.random.permutation(key, n - num_top)[:num_random]
        keep = jnp.concatenate([keep, order[:, num_top:][:, pick]], axis=1)

    def take(a: Array) -> Array:
        return jnp.take_along_axis(a, keep.reshape(b, -1, *([1] * (a.ndim - 2))), axis=1)

    return Gaussians(*(take(a) for a in gaussians))
