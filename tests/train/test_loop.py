"""run_stage (llrmpp_jax.train.loop): the one stage loop of the trainer and the notebooks.

A counting step function (state = the sum of the batches seen) stands in for a train step,
so what the loop does is checked exactly: one batch per step from ``start`` to ``steps``,
every hook after every step in order, ``last`` on the final step, ``stop`` asked after
each step and ending the stage after that step's hooks, nothing read beyond the last step.
"""

import itertools

from llrmpp_jax.train.loop import StageRun, run_stage


def _step(state, batch):
    return state + batch, {"loss": float(batch)}


def test_runs_from_start_to_steps_calling_each_hook_in_order():
    calls, pulled = [], []

    def batches():
        for b in itertools.count(10):
            pulled.append(b)
            yield b

    def first(info):
        calls.append(("first", info.step, info.state, info.metrics["loss"], info.last, info.stopping))

    def second(info):
        calls.append(("second", info.step))

    done = run_stage(100, _step, batches(), steps=5, start=2, hooks=[first, second])
    assert done == StageRun(state=100 + 10 + 11 + 12, step=5, stopped=False)
    assert pulled == [10, 11, 12]  # one batch per step, none read ahead
    assert calls == [
        ("first", 3, 110, 10.0, False, False),
        ("second", 3),
        ("first", 4, 121, 11.0, False, False),
        ("second", 4),
        ("first", 5, 133, 12.0, True, False),
        ("second", 5),
    ]


def test_stop_ends_the_stage_after_the_step_and_its_hooks():
    seen, asked = [], []

    def stop():
        asked.append(len(seen))
        return len(asked) == 2  # asked before the hooks of each step

    done = run_stage(
        0, _step, itertools.count(1), steps=10, hooks=[lambda i: seen.append((i.step, i.last, i.stopping))], stop=stop
    )
    assert done == StageRun(state=1 + 2, step=2, stopped=True)
    assert asked == [0, 1] and seen == [(1, False, False), (2, True, True)]


def test_a_finished_stage_runs_nothing():
    done = run_stage(7, _step, iter(()), steps=3, start=3, hooks=[lambda i: 1 / 0], stop=lambda: 1 / 0)  # pyright: ignore[reportArgumentType] -- a hook may return a value; run_stage ignores it
    assert done == StageRun(state=7, step=3, stopped=False)
