"""``jax.vmap`` that runs a function once per batch element instead of batching it.

``vmap`` of a ``while_loop`` whose trip count differs across the batch runs every element
to the longest count and selects each loop carry on every step, and ``vmap`` of a
``lax.cond`` evaluates both branches. The splatter's loops and branches skip work that a
batch element does not need, so they are wrapped here: under ``vmap`` (over cameras,
scenes or partition copies) they cost the sum of the single calls.
"""

from __future__ import annotations

from collections.abc import Callable

import jax
from jax import lax
from jax.custom_batching import custom_vmap


def sequential_over_batch(fn: Callable) -> Callable:
    """``fn`` (positional array pytrees in and out) whose ``jax.vmap`` is ``lax.map`` over
    the batched arguments, the unbatched ones shared; every output is batched."""
    wrapped = custom_vmap(fn)

    @wrapped.def_vmap
    def _rule(axis_size, in_batched, *args):
        del axis_size
        leaves, tree = jax.tree.flatten(args)
        flags = jax.tree.leaves(in_batched)

        def one(batched_leaves):
            it = iter(batched_leaves)
            return wrapped(*jax.tree.unflatten(tree, [next(it) if b else x for x, b in zip(leaves, flags)]))

        out = lax.map(one, [x for x, b in zip(leaves, flags) if b])
        return out, jax.tree.map(lambda _: True, out)

    return wrapped
