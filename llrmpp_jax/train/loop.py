"""One training stage, without files: :func:`run_stage` steps a train state through a
batch iterator and calls hooks after every step.

Everything else a run does around its steps is a hook: the trainer's progress bar, log,
checkpoints and held-out evaluation (:func:`llrmpp_jax.trainer.train`), the ablation
notebooks' loss curve and parameter snapshots. A hook gets a :class:`StepInfo` (the step
just done, the new state, its metrics, whether it is the last one); ``stop`` ends the
stage early after the current step, whose hooks then see ``last=True``.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass
from typing import Any


@dataclass(frozen=True)
class StepInfo:
    """What a hook sees after a step: ``step`` (steps done in the stage, 1 after the
    first), the ``state`` and ``metrics`` the step function returned (device arrays, as
    they are: replicated or sharded), and ``last``: the stage ends after this step (its
    final step, or ``stop`` asked for it, then ``stopping`` is True)."""

    step: int
    state: Any
    metrics: dict[str, Any]
    last: bool
    stopping: bool


Hook = Callable[[StepInfo], None]


@dataclass(frozen=True)
class StageRun:
    """The end of :func:`run_stage`: the last ``state``, the ``step`` it reached and
    whether ``stop`` ended it early (``stopped``)."""

    state: Any
    step: int
    stopped: bool


def run_stage(
    state: Any,
    step_fn: Callable[[Any, Any], tuple[Any, dict]],
    batches: Iterable[Any],
    *,
    steps: int,
    start: int = 0,
    hooks: Sequence[Hook] = (),
    stop: Callable[[], bool] | None = None,
) -> StageRun:
    """Run ``step_fn(state, batch) -> (state, metrics)`` on the next batch of ``batches``
    from step ``start`` until ``steps``, calling each hook in order after every step.
    ``stop()`` is asked after each step, before its hooks: True makes it the last one.

    The batches must continue where step ``start`` left off (a resumed iterator); nothing
    is read or written here."""
    batches = iter(batches)
    step, stopping = start, False
    while step < steps:
        state, metrics = step_fn(state, next(batches))
        step += 1
        stopping = stop is not None and bool(stop())
        info = StepInfo(step, state, metrics, last=step == steps or stopping, stopping=stopping)
        for hook in hooks:
            hook(info)
        if stopping:
            break
    return StageRun(state, step, stopping)
