"""Long-LRM's optimiser as an optax transformation: clip -> AdamW with masked decay.

Recipe (reference facts §2.1): ``torch.optim.AdamW(lr=4e-4, betas=(0.9, 0.95), eps=1e-8)``
with weight decay 0.05 on every parameter of rank >= 2 only (biases, norms and the
Mamba2 ``A_log`` / ``dt_bias`` / ``D`` vectors are not decayed), global-norm clipping at
10, and HF ``get_cosine_schedule_with_warmup``: linear warmup from 0 to ``lr``, then a
half cosine down to 0 at ``total_steps``.

The schedule is indexed by optax's own count, which advances with every applied update
and, through :func:`advance_schedule`, with every update skipped for a too-large
gradient norm: the PyTorch scheduler steps on those (Long-LRM skips ``optimizer.step()``
but still calls ``scheduler.step()``) and not on non-finite steps.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass

import jax
import jax.numpy as jnp
import numpy as np
import optax

from llrmpp_jax.array_typing import Array, ArrayLike, Float, Int
from llrmpp_jax.errors import UserError
from llrmpp_jax.train.spikes import skip_gradient_spikes

# Long-LRM's ``training.train_steps`` in every released config: the horizon of its cosine.
LONG_LRM_TRAIN_STEPS = 1_000_000


@dataclass(frozen=True)
class OptimizerConfig:
    """Hyper-parameters of :func:`make_optimizer` (defaults: Long-LRM ``7m1t_tm.yaml``).

    ``no_decay_names`` lists parameter-path components (e.g. ``"A_log"``, ``"dt_bias"``,
    ``"global_tokens"``) whose leaves are never decayed, whatever their rank.
    ``grad_clip_norm`` of ``None`` disables clipping.
    """

    lr: float = 4e-4
    b1: float = 0.9
    b2: float = 0.95
    eps: float = 1e-8
    weight_decay: float = 0.05
    no_decay_names: tuple[str, ...] = ()
    warmup_steps: int = 2000
    total_steps: int = LONG_LRM_TRAIN_STEPS
    grad_clip_norm: float | None = 10.0
    # Skip updates whose gradient norm exceeds this many times the recent (geometric) mean
    # norm (train/spikes.py); None: Long-LRM's absolute guards only.
    spike_factor: float | None = None

    def __post_init__(self) -> None:
        if self.warmup_steps < 0:
            raise UserError(f"OptimizerConfig: warmup_steps={self.warmup_steps} must be >= 0")
        if self.total_steps < max(self.warmup_steps, 1):
            raise UserError(
                f"OptimizerConfig: total_steps={self.total_steps} must be >= max(1, warmup_steps={self.warmup_steps})"
            )
        if self.spike_factor is not None and self.spike_factor <= 1:
            raise UserError(f"OptimizerConfig: spike_factor={self.spike_factor} must be > 1 or None")
        if self.grad_clip_norm is not None and self.grad_clip_norm <= 0:
            raise UserError(f"OptimizerConfig: grad_clip_norm={self.grad_clip_norm} must be > 0 or None")
        if isinstance(self.no_decay_names, str):
            raise UserError(
                f"OptimizerConfig: no_decay_names must be a tuple of names, got the string {self.no_decay_names!r}"
            )


def warmup_cosine_schedule(lr: float, warmup_steps: int, total_steps: int) -> optax.Schedule:
    """HF ``get_cosine_schedule_with_warmup`` as a function of the update count.

    ``count < warmup``: ``lr * count / warmup``; then ``lr * 0.5 * (1 + cos(pi * p))``
    with ``p = (count - warmup) / (total - warmup)``. ``p`` is clamped to 1, so the rate
    stays 0 after ``total_steps`` (HF's formula would rise again). Returns float32.
    """
    warm = float(max(1, warmup_steps))
    span = float(max(1, total_steps - warmup_steps))

    def schedule(count: int | Int[ArrayLike, ""]) -> Float[Array, ""]:
        step = jnp.asarray(count).astype(jnp.float32)
        ramp = step / warm
        # 0.5 * (1 + cos(pi p)) written as sin(pi (1 - p) / 2)^2 with 1 - p computed
        # directly: no float32 cancellation as the rate approaches 0 at the end.
        remaining = jnp.clip((float(warmup_steps) + span - step) / span, 0.0, 1.0)
        cosine = jnp.square(jnp.sin(np.float32(np.pi / 2) * remaining))
        return (lr * jnp.where(step < float(warmup_steps), ramp, cosine)).astype(jnp.float32)

    return schedule  # pyright: ignore[reportReturnType] -- a function of the step count is an optax schedule


def _path_names(path: tuple) -> tuple[str, ...]:
    """Key-path entries (dict keys, attribute names, sequence indices) as strings."""
    names = []
    for entry in path:
        for attr in ("key", "name", "idx"):
            if hasattr(entry, attr):
                names.append(str(getattr(entry, attr)))
                break
    return tuple(names)


def weight_decay_mask(params, no_decay_names: tuple[str, ...] = ()):
    """Pytree of bools like ``params``: True where AdamW decays the leaf.

    A leaf is decayed when its rank is >= 2 and no component of its path is in
    ``no_decay_names`` (Long-LRM's ``dim() == 1`` / ``_no_weight_decay`` groups).
    """
    banned = frozenset(no_decay_names)

    def decays(path, leaf) -> bool:
        return jnp.ndim(leaf) >= 2 and banned.isdisjoint(_path_names(path))

    return jax.tree_util.tree_map_with_path(decays, params)


def make_schedule(cfg: OptimizerConfig) -> optax.Schedule:
    """The learning-rate schedule of ``cfg`` (see :func:`warmup_cosine_schedule`)."""
    return warmup_cosine_schedule(cfg.lr, cfg.warmup_steps, cfg.total_steps)


def make_optimizer(cfg: OptimizerConfig) -> optax.GradientTransformation:
    """Global-norm clip, then AdamW (decoupled decay on :func:`weight_decay_mask` leaves),
    inside :func:`~llrmpp_jax.train.spikes.skip_gradient_spikes` when ``cfg.spike_factor``
    is set.

    Matches ``clip_grad_norm_`` + ``torch.optim.AdamW`` + the HF schedule step for step
    (the clip factor differs from torch's ``max / (norm + 1e-6)`` by ~1e-6 relative).
    """
    adamw = optax.adamw(
        make_schedule(cfg),
        b1=cfg.b1,
        b2=cfg.b2,
        eps=cfg.eps,
        weight_decay=cfg.weight_decay,
        mask=functools.partial(weight_decay_mask, no_decay_names=cfg.no_decay_names),
    )
    opt = adamw if cfg.grad_clip_norm is None else optax.chain(optax.clip_by_global_norm(cfg.grad_clip_norm), adamw)
    return opt if cfg.spike_factor is None else skip_gradient_spikes(opt, cfg.spike_factor)


def _is_schedule_state(node) -> bool:
    return isinstance(node, optax.ScaleByScheduleState)


def schedule_count(opt_state: optax.OptState) -> Int[Array, ""] | None:
    """The learning-rate schedule's step count held in ``opt_state`` (the count of its
    first ``ScaleByScheduleState``), or ``None`` if the optimizer has no schedule."""
    found = [n for n in jax.tree.leaves(opt_state, is_leaf=_is_schedule_state) if _is_schedule_state(n)]
    return found[0].count if found else None


def advance_schedule(opt_state: optax.OptState) -> optax.OptState:
    """``opt_state`` with every learning-rate schedule one step further and all else
    (Adam moments and their bias-correction count) unchanged: a skipped update after
    which ``scheduler.step()`` still ran."""
    return jax.tree.map(
        lambda n: n._replace(count=optax.safe_increment(n.count)) if _is_schedule_state(n) else n,
        opt_state,
        is_leaf=_is_schedule_state,
    )
