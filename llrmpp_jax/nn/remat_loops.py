"""Remat'd block stacks as loops: a stack of blocks whose backward pass runs block by block.

A stack of ``jax.checkpoint``-ed blocks bounds what the forward pass keeps, not what the
backward pass holds at once: XLA may schedule the recomputations and gradients of many
blocks together. Run as a ``lax.scan``, the backward is a loop whose iteration holds one
block (or one repetition of a block pattern). Parameters stay one subtree per block (the
checkpoint layout); they are stacked in the forward pass.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import flax.linen as nn
import jax
import jax.numpy as jnp

from llrmpp_jax.array_typing import Array, Float


def block_runs(layout: str) -> list[tuple[int, str, int]]:
    """Maximal runs of consecutive same-kind blocks as ``(first index, kind, length)``:
    ``block_runs("TMMMT")`` -> ``[(0, "T", 1), (1, "M", 3), (4, "T", 1)]``."""
    runs: list[tuple[int, str, int]] = []
    for i, kind in enumerate(layout):
        if runs and runs[-1][1] == kind:
            runs[-1] = (runs[-1][0], kind, runs[-1][2] + 1)
        else:
            runs.append((i, kind, 1))
    return runs


def layout_period(kinds: str) -> int:
    """Length of the shortest ``period`` with ``kinds == period * k``: ``"TMMTMM"`` -> 3."""
    n = len(kinds)
    return next(p for p in range(1, n + 1) if n % p == 0 and kinds[:p] * (n // p) == kinds)


def remat_after_cotangent(f: Callable[[Any, Any], Array]) -> Callable[[Any, Any], Array]:
    """``jax.checkpoint(f)`` for ``f(h, w)`` (``h`` an array or a tuple of arrays, the
    output one array): the forward keeps only ``h`` and ``w``, the backward recomputes ``f``
    and differentiates it, but not before the output's cotangent exists.

    The recomputation is made to read the cotangent through the parameters (``w + 0 *
    ct[0]``: XLA does not fold a float multiply by zero, it would change NaN/inf; ``w`` is
    small, ``h`` may be large), so XLA cannot schedule it early.
    With ``jax.checkpoint`` it could, and did: inside the loop over the backbone's
    ``T M M M M M M M`` pattern, XLA:CPU recomputed the ``T`` block before running the
    seven ``M`` blocks' backward loop and held its activations (tens of GB) through it.
    """

    @jax.custom_vjp
    def g(h, w):
        return f(h, w)

    def fwd(h, w):
        return f(h, w), (h, w)

    def bwd(res, ct):
        h, w = res
        zero = ct.reshape(-1)[0] * 0
        w = jax.tree.map(lambda a: a + zero.astype(a.dtype), w)
        return jax.vjp(f, h, w)[1](ct)

    g.defvjp(fwd, bwd)
    return g


def remat_blocks(
    kinds: str, make: Callable[[str], nn.Module], params: list, x: Float[Array, "B L D"]
) -> Float[Array, "B L D"]:
    """``x`` through the blocks ``make(kinds[i])`` (unbound modules) with parameter trees
    ``params[i]``, each block rematerialised (:func:`remat_after_cotangent`), as loops
    rather than unrolled code.

    A layout that repeats a period (``"TMMMMMMM" * 3``; a run of one kind is a period of
    one) runs as one ``lax.scan`` over the repetitions, with the period's parameter trees
    stacked (``jnp.stack`` here, in the forward, so the stored layout stays one subtree per
    block as checkpoints expect) and the period itself applied the same way, recursively;
    otherwise the runs of one kind follow each other. Same numbers as the blocks applied one
    after another, but the backward pass is a loop that holds one repetition's blocks at a
    time: unrolled, XLA:CPU's scheduler interleaved the blocks' backward passes and held
    the buffers of all 24 paper backbone blocks at once (docs/results.md, "Memory analysis
    of the stage-4 step").
    """
    n, period = len(kinds), layout_period(kinds)
    if n == 1:
        block = make(kinds)
        return remat_after_cotangent(lambda h, w: block.apply({"params": w}, h))(x, params[0])  # pyright: ignore[reportArgumentType] -- apply without mutable= returns the output alone
    if period < n:
        stacked = [jax.tree.map(lambda *a: jnp.stack(a), *params[j::period]) for j in range(period)]

        def step(h, ws):
            return remat_blocks(kinds[:period], make, ws, h), None

        return jax.lax.scan(step, x, stacked)[0]
    for start, _, count in block_runs(kinds):
        x = remat_blocks(kinds[start : start + count], make, params[start : start + count], x)
    return x
