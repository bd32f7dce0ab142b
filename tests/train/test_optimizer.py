"""Optimizer and schedule against plain-Python HF and torch.optim.AdamW oracles."""

import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest
import torch

from llrmpp_jax.train.optimizer import (
    OptimizerConfig,
    make_optimizer,
    warmup_cosine_schedule,
    weight_decay_mask,
)
from tests.helpers.typechecks import unchecked


def hf_cosine_with_warmup(step: int, warmup: int, total: int) -> float:
    """transformers.get_cosine_schedule_with_warmup's lr_lambda (num_cycles=0.5), verbatim."""
    if step < warmup:
        return float(step) / float(max(1, warmup))
    progress = float(step - warmup) / float(max(1, total - warmup))
    return max(0.0, 0.5 * (1.0 + math.cos(math.pi * 0.5 * 2.0 * progress)))


@pytest.mark.parametrize("warmup,total", [(5, 20), (0, 7), (3, 3)])
def test_schedule_matches_hf(warmup, total):
    lr = 4e-4
    sched = jax.jit(warmup_cosine_schedule(lr, warmup, total))
    for step in range(total + 1):
        got = float(sched(jnp.asarray(step, jnp.int32)))
        want = lr * hf_cosine_with_warmup(step, warmup, total)
        assert got == pytest.approx(want, rel=1e-6, abs=1e-12), step
    # Past total_steps HF's half cosine would climb back; ours stays at 0.
    for step in range(total + 1, total + 5):
        assert float(sched(jnp.asarray(step, jnp.int32))) == pytest.approx(0.0, abs=1e-12)
    assert sched(jnp.asarray(1, jnp.int32)).dtype == jnp.float32


def test_weight_decay_mask():
    params = {
        "embed": {"kernel": jnp.ones((4, 3)), "bias": jnp.ones((3,))},
        "mamba": {"A_log": jnp.ones((2, 5)), "conv": jnp.ones((4, 1, 6)), "D": jnp.ones((2,))},
        "blocks": [{"scale": jnp.ones((3,)), "w": jnp.ones((3, 3))}],
    }
    got = weight_decay_mask(params, no_decay_names=("A_log",))
    want = {
        "embed": {"kernel": True, "bias": False},
        "mamba": {"A_log": False, "conv": True, "D": False},
        "blocks": [{"scale": False, "w": True}],
    }
    assert got == want
    # Without the name-based set, the 2-D A_log is decayed like any matrix.
    assert weight_decay_mask(params)["mamba"]["A_log"] is True


def test_matches_torch_adamw(rng):
    """30 steps of clip + AdamW (two param groups) + HF schedule vs torch, in float64."""
    cfg = OptimizerConfig(
        lr=3e-2,
        warmup_steps=4,
        total_steps=30,
        weight_decay=0.05,
        grad_clip_norm=10.0,
        no_decay_names=("nodecay",),
    )
    shapes = {"a": (4, 3), "b": (3,), "nodecay": (2, 2), "c": (2, 3, 2)}
    init = {k: rng.normal(size=s) for k, s in shapes.items()}
    grads_seq = [{k: rng.normal(size=s) * (30.0 if i % 3 == 0 else 0.5) for k, s in shapes.items()} for i in range(30)]

    tx = make_optimizer(cfg)
    params = {k: jnp.asarray(v, jnp.float64) for k, v in init.items()}
    with jax.numpy_dtype_promotion("standard"):
        opt_state = tx.init(params)
        update = jax.jit(tx.update)
        for g in grads_seq:
            updates, opt_state = update({k: jnp.asarray(v) for k, v in g.items()}, opt_state, params)
            params = jax.tree.map(lambda p, u: p + u, params, updates)

    tp = {k: torch.tensor(v, dtype=torch.float64, requires_grad=True) for k, v in init.items()}
    decay = [tp[k] for k in ("a", "c")]
    no_decay = [tp[k] for k in ("b", "nodecay")]
    opt = torch.optim.AdamW(
        [{"params": decay, "weight_decay": cfg.weight_decay}, {"params": no_decay, "weight_decay": 0.0}],
        lr=cfg.lr,
        betas=(cfg.b1, cfg.b2),
        eps=cfg.eps,
    )
    sched = torch.optim.lr_scheduler.LambdaLR(
        opt, lambda s: hf_cosine_with_warmup(s, cfg.warmup_steps, cfg.total_steps)
    )
    for g in grads_seq:
        for k, t in tp.items():
            t.grad = torch.tensor(g[k], dtype=torch.float64)
        torch.nn.utils.clip_grad_norm_(list(tp.values()), cfg.grad_clip_norm)  # pyright: ignore[reportArgumentType] -- CFG sets grad_clip_norm
        opt.step()
        sched.step()

    for k in shapes:
        np.testing.assert_allclose(np.asarray(params[k]), tp[k].detach().numpy(), rtol=0, atol=1e-7)


def test_config_errors():
    with pytest.raises(ValueError, match="total_steps=5 must be >= max"):
        OptimizerConfig(warmup_steps=10, total_steps=5)
    with pytest.raises(ValueError, match="warmup_steps=-1"):
        OptimizerConfig(warmup_steps=-1)
    with pytest.raises(ValueError, match="grad_clip_norm=0"):
        OptimizerConfig(grad_clip_norm=0.0)
    with pytest.raises(ValueError, match="no_decay_names must be a tuple"), unchecked():
        OptimizerConfig(no_decay_names="A_log")  # pyright: ignore[reportArgumentType] -- a bad value on purpose: the test wants its error
