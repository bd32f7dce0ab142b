"""Post-prediction optimisation of predicted Gaussians (paper Table 1: "Long-LRM_10").

Starting from ``model.reconstruct``'s Gaussians, a few Adam steps fit them to the *input*
views with the training's RGB loss (``losses.rgb_loss``: MSE + ``perceptual_weight`` x
perceptual; no depth term, as there are no depth targets at test time). Optimised, per
Gaussian, in unconstrained form:

* ``means`` (scene units), ``log_scales``, ``quats`` (raw, normalised when rendering),
  ``opacity_logits``;
* colour mode: the SH coefficients, as ``sh_dc`` (coefficient 0) and ``sh_rest`` (the
  others, with 3DGS's 20x smaller learning rate so view-dependent colour does not overfit
  the inputs); feature mode: ``features``, with the decoder (and the partition linear)
  frozen, rendered through the model's own ``model.render``.

The log-scale is not clamped at ``cfg.head.scale_max`` (a hard clamp has zero gradient
above it); opacities are clipped to ``[2^-24, 1 - 2^-24]`` before the logit, as in
``export_ply``.

Views per step. Like 3DGS (one view per step), each update fits a fresh random subset of
``RefineConfig.views_per_step`` input views (drawn without replacement from the caller's
PRNG key), so a step costs the same with 8 inputs or 64. The subset's size is static,
so nothing recompiles; with ``views_per_step >= V`` every step fits all V views (the
paper's setting, exactly the full-batch fit). The default, 8, covers the procedural
scenes' 8 inputs, so their 10-step numbers are the full-batch ones; a 32-input capture
fits 8 views a step (``docs/results.md``, "Refinement").

Splat buffer. The splat capacity is fitted to the scene before the first step
(:func:`llrmpp_jax.model.fit_capacity` at the input views with the starting Gaussians, with
``RefineConfig.capacity_headroom``: Gaussians move and grow during the fit; overflow is
still counted in ``RefineInfo.dropped``). A config that sets ``splat.max_intersections``
keeps it.

Solver. ``optimistix.OptaxMinimiser`` around ``optax.multi_transform`` of one Adam per
field (learning rates in :class:`RefineConfig`), driven through optimistix's iterative
API (``solver.init`` once, a jitted ``solver.step`` per iteration, ``solver.terminate``
checked after each) rather than ``optimistix.minimise``: the same solver and stopping
rule as ``minimise(..., max_steps=steps)``, but the Python loop can drive a progress bar
and record the loss of every step. ``rtol = atol = 0`` (the default) never stops early,
so exactly ``steps`` updates are taken, as in Long-LRM's fixed-step optimisation. (The
stopping rule compares successive subset losses when ``views_per_step < V``.)
"""

from __future__ import annotations

import dataclasses
import functools
import time
from dataclasses import dataclass
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
import optax
import optimistix as optx
from tqdm.auto import tqdm

from llrmpp_jax.array_typing import Array, ArrayLike, Float, KeyArray
from llrmpp_jax.compile_cache import CompileWatch
from llrmpp_jax.config import ModelConfig
from llrmpp_jax.errors import UserError
from llrmpp_jax.gaussians import OPACITY_LOGIT_EPS, Gaussians
from llrmpp_jax.losses import rgb_loss
from llrmpp_jax.metrics import psnr
from llrmpp_jax.model import fit_capacity, render
from llrmpp_jax.perceptual import VGGParams


@dataclass(frozen=True)
class RefineConfig:
    """Adam learning rates per field (normalised scene frame: input cameras in
    ``[-1, 1]^3``), times ``rate_scale``; loss weights and optimistix's stopping tolerances.
    Hashable: a static argument of the jitted step.

    The per-field rates are those of a 100-step fit: 3DGS's for quaternions (1e-3) and its
    SH rest/DC ratio (1/20); log-scales 3x 3DGS's 5e-3; means, opacity and features move
    faster than 3DGS's 30k-step schedule would (its means start at 1.6e-4 x extent).
    ``rate_scale=None`` (the default) takes :func:`rate_scale_for` the number of steps: a
    shorter fit takes larger steps.

    Each field's rate was then varied alone around the 10-step default on validation
    scenes: only the log-scales' larger rate gained on held-out PSNR and LPIPS alike, at 10,
    30 and 100 steps, so it is the default (docs/lab-notes.md, "Refinement rates").
    """

    lr_means: float = 1e-3
    lr_log_scales: float = 1.5e-2
    lr_quats: float = 1e-3
    lr_opacity_logits: float = 5e-2
    lr_features: float = 5e-3  # feature mode: features; colour mode: SH coefficient 0
    sh_rest_lr_factor: float = 1.0 / 20.0  # colour mode: SH coefficients 1.. (3DGS's ratio)
    rate_scale: float | None = None  # every rate times this; None: rate_scale_for(steps)
    perceptual_weight: float = 0.0  # the paper trains with 0.5 (needs VGG params)
    views_per_step: int = 8  # input views fitted per update (a random subset; all when >= V)
    capacity_headroom: float = 1.25  # splat capacity: this x the starting Gaussians' most-needed slots
    rtol: float = 0.0
    atol: float = 0.0

    def __post_init__(self) -> None:
        if self.views_per_step < 1:
            raise UserError(f"RefineConfig.views_per_step must be >= 1, got {self.views_per_step}")


def rate_scale_for(steps: int) -> float:
    """The default factor on :class:`RefineConfig`'s rates for a fit of ``steps`` updates:
    ``100 / steps`` clipped to ``[1, 10]``, so a fit of 10-100 steps moves each field about as
    far in all (Adam's step is ~ its rate).

    Chosen on validation procedural scenes (seeds apart from the held-out ones) with the
    feature-mode ``pretrained:small`` (``experiments/bench_refine_rates.py`` in a checkout):
    larger factors gain at 10 and 30 steps until about x30, where they stop gaining and x100
    diverges; at 100 steps they over-fit the inputs, so the factor stops at 1. Colour mode
    was not swept; the same rule helps the golden Long-LRM's colour refinement on real
    captures (docs/lab-notes.md, "Refinement rates").
    """
    return float(min(10.0, max(1.0, 100.0 / max(steps, 1))))


class RefineInfo(NamedTuple):
    """``losses[i]`` (``i < steps``) is the loss of update i's views before it, and
    ``losses[-1]`` the loss of the first update's views after the last update, so
    ``losses[0] -> losses[-1]`` compares the same views. With ``views_per_step >= V`` every
    update fits all V views and these are the input-view losses. (The whole input set is
    not scored in one program: on a 32-view capture that alone would take about as long as
    four updates and most of the memory.)"""

    losses: Float[np.ndarray, " steps+1"]
    steps: int  # updates taken (fewer than asked only if the solver's tolerances were met)
    dropped: int  # most splat intersections dropped by any step's render (0 = exact)
    views_per_step: int = 0  # input views each update fitted
    capacity: int = 0  # the splat buffer the fit used (slots per rendered view)
    compile_s: float = 0.0  # wall time to compile the step
    step_s: float = 0.0  # median wall time of one update after the first
    compile_note: str = ""  # the compile's seconds and whether it came from the compile cache


def to_unconstrained(gaussians: Gaussians, cfg: ModelConfig) -> dict[str, Array]:
    """The optimised pytree (module docstring) of render-ready Gaussians."""
    o = jnp.clip(gaussians.opacities, OPACITY_LOGIT_EPS, 1.0 - OPACITY_LOGIT_EPS)
    y = {
        "means": gaussians.means,
        "log_scales": jnp.log(gaussians.scales),
        "quats": gaussians.quats,
        "opacity_logits": jnp.log(o) - jnp.log1p(-o),
    }
    if cfg.head.mode == "color":
        y["sh_dc"], y["sh_rest"] = gaussians.features[..., :3], gaussians.features[..., 3:]
    else:
        y["features"] = gaussians.features
    return y


def from_unconstrained(y: dict[str, Array]) -> Gaussians:
    """Inverse of :func:`to_unconstrained` (quaternions normalised)."""
    q = y["quats"]
    q = q * jax.lax.rsqrt(jnp.maximum(jnp.sum(jnp.square(q), axis=-1, keepdims=True), 1e-24))
    features = jnp.concatenate([y["sh_dc"], y["sh_rest"]], axis=-1) if "sh_dc" in y else y["features"]
    return Gaussians(
        means=y["means"],
        quats=q,
        scales=jnp.exp(y["log_scales"]),
        opacities=jax.nn.sigmoid(y["opacity_logits"]),
        features=features,
    )


def _optimizer(rc: RefineConfig) -> optax.GradientTransformation:
    """One Adam per field; ``rc.rate_scale`` must be resolved (:func:`refine` does)."""
    lrs = {
        "means": rc.lr_means,
        "log_scales": rc.lr_log_scales,
        "quats": rc.lr_quats,
        "opacity_logits": rc.lr_opacity_logits,
        "features": rc.lr_features,
        "sh_dc": rc.lr_features,
        "sh_rest": rc.lr_features * rc.sh_rest_lr_factor,
    }
    tx = optax.multi_transform({k: optax.adam(v * rc.rate_scale) for k, v in lrs.items()}, lambda y: {k: k for k in y})  # pyright: ignore[reportOperatorIssue] -- refine resolves rate_scale before this (the docstring's contract)

    def update(updates, state, params=None, **extra):
        # optax mixes Python floats with its int32 count (``b1 ** count``), which strict
        # promotion rejects; its outputs keep the parameters' float32 (as train/step.py).
        with jax.numpy_dtype_promotion("standard"):
            return tx.update(updates, state, params, **extra)

    return optax.GradientTransformationExtraArgs(tx.init, update)


def _solver(rc: RefineConfig) -> optx.OptaxMinimiser:
    return optx.OptaxMinimiser(_optimizer(rc), rtol=rc.rtol, atol=rc.atol)


def objective(cfg: ModelConfig, rc: RefineConfig):
    """The refinement's objective ``fn(y, args) -> (loss, aux)`` over the unconstrained
    Gaussians ``y`` (:func:`to_unconstrained`), ``args = (params, images, c2w, intrinsics,
    vgg)``; aux holds the batch's ``psnr`` and the splat's ``dropped`` count."""

    def fn(y, args):
        params, images, c2w, intrinsics, vgg = args
        h, w = images.shape[2:4]
        out = render(params, cfg, from_unconstrained(y), c2w, intrinsics, h, w, ("rgb",))
        loss, aux = rgb_loss(
            out.images["rgb"].reshape(-1, h, w, 3),
            images.reshape(-1, h, w, 3),
            vgg,
            perceptual_weight=rc.perceptual_weight,
        )
        return loss, {"psnr": aux["psnr"], "dropped": jnp.max(out.dropped)}

    return fn


_TAGS = frozenset()


def _subset(args, idx: Array | None):
    """``args`` with only the input views ``idx`` (``None``: all)."""
    if idx is None:
        return args
    params, images, c2w, intrinsics, vgg = args
    return params, images[:, idx], c2w[:, idx], intrinsics[:, idx], vgg


def _views(key: KeyArray, step: Array, num_views: int, per_step: int) -> Array | None:
    """Update ``step``'s views: ``per_step`` distinct indices in ``[0, num_views)``."""
    if per_step >= num_views:
        return None
    return jax.random.permutation(jax.random.fold_in(key, step), num_views)[:per_step]


@functools.partial(jax.jit, static_argnames=("cfg", "rc"))
def _init(y, args, cfg: ModelConfig, rc: RefineConfig):
    fn = objective(cfg, rc)
    sub = _subset(args, _views(jax.random.key(0), jnp.int32(0), args[1].shape[1], rc.views_per_step))
    f_struct, aux_struct = jax.eval_shape(fn, y, sub)
    return _solver(rc).init(fn, y, sub, {}, f_struct, aux_struct, _TAGS)


@functools.partial(jax.jit, static_argnames=("cfg", "rc"), donate_argnames=("y", "state"))
def _step(y, state, args, key, step, cfg: ModelConfig, rc: RefineConfig):
    fn, solver = objective(cfg, rc), _solver(rc)
    sub = _subset(args, _views(key, step, args[1].shape[1], rc.views_per_step))
    y, state, aux = solver.step(fn, y, sub, {}, state, _TAGS)
    done, _ = solver.terminate(fn, y, sub, {}, state, _TAGS)
    return y, state, aux, done


@functools.partial(jax.jit, static_argnames=("cfg", "rc"))
def _loss(y, args, cfg: ModelConfig, rc: RefineConfig):
    return objective(cfg, rc)(y, args)


def refine(
    params: dict,
    cfg: ModelConfig,
    gaussians: Gaussians,
    images: Float[ArrayLike, "B V H W 3"],
    c2w: Float[ArrayLike, "B V 4 4"],
    intrinsics: Float[ArrayLike, "B V 4"],
    steps: int = 10,
    rc: RefineConfig = RefineConfig(),
    vgg_params: VGGParams | None = None,
    progress: bool = False,
    key: KeyArray | None = None,
) -> tuple[Gaussians, RefineInfo]:
    """Optimise ``gaussians`` (``[B, N, ...]``, scene frame) against the input views.

    Args:
      params: the model's parameters; only feature mode reads them (the frozen decoder
        and partition linear), colour mode may pass ``{}``.
      cfg: the model's config (static); its splat capacity is fitted to the scene
        (module docstring).
      gaussians: ``model.reconstruct``'s output for these inputs.
      images, c2w, intrinsics: the input views in [0, 1] and their cameras (the loss targets).
      steps: the most updates to take (optimistix's ``max_steps``).
      rc: learning rates, loss weights, views per step and tolerances.
      vgg_params: needed only when ``rc.perceptual_weight > 0``.
      progress: show a tqdm bar: "compiling", then the updates with their rate and loss,
        and a line with the expected time once the first update has run.
      key: draws each update's views (``jax.random.key(0)`` when omitted); unused when
        ``rc.views_per_step >= V``.

    Returns:
      ``(refined Gaussians, RefineInfo)``; one jitted step per update (compiled once per
      config and shape).
    """
    if steps < 0:
        raise UserError(f"refine: steps must be >= 0, got {steps}")
    if rc.perceptual_weight and vgg_params is None:
        raise UserError(f"refine: perceptual_weight={rc.perceptual_weight} needs vgg_params")
    if rc.rate_scale is None:
        rc = dataclasses.replace(rc, rate_scale=rate_scale_for(steps))
    num_views = int(images.shape[1])
    rc = dataclasses.replace(rc, views_per_step=min(rc.views_per_step, num_views))
    key = jax.random.key(0) if key is None else key
    h, w = int(images.shape[2]), int(images.shape[3])
    args = (params, jnp.asarray(images), jnp.asarray(c2w), jnp.asarray(intrinsics), vgg_params)
    gaussians = jax.tree.map(jnp.asarray, gaussians)
    cfg = fit_capacity(params, cfg, gaussians, args[2], args[3], h, w, headroom=rc.capacity_headroom)
    # Fresh buffers: the step donates y, which must not alias the caller's arrays.
    y = jax.tree.map(jnp.array, to_unconstrained(gaussians, cfg))
    state = _init(y, args, cfg, rc)
    losses, dropped, taken, times = [], 0, 0, []
    with tqdm(total=steps, desc="refine (compiling)", disable=not progress, dynamic_ncols=True) as bar:
        t0 = time.perf_counter()
        with CompileWatch() as watch:
            step_fn = _step.lower(y, state, args, key, jnp.int32(0), cfg, rc).compile()
        compile_s = time.perf_counter() - t0
        compile_note = watch.describe(compile_s)
        bar.set_description("refine")
        for i in range(steps):
            t0 = time.perf_counter()
            y, state, aux, done = step_fn(y, state, args, key, jnp.int32(i))
            losses.append(float(state.f))  # the loss at the iterate this step started from
            dropped = max(dropped, int(aux["dropped"]))
            times.append(time.perf_counter() - t0)
            taken += 1
            if i == 0 and progress:
                bar.write(
                    f"refine: {steps} updates of {rc.views_per_step}/{num_views} views at {h}x{w}, "
                    f"~{times[0]:.1f} s each: about {steps * times[0]:.0f} s "
                    f"(compiled: {compile_note})"
                )
            bar.update(1)
            bar.set_postfix(loss=f"{losses[-1]:.5f}", psnr=f"{float(aux['psnr']):.2f}")
            if bool(done):
                break
    first_views = _subset(args, _views(key, jnp.int32(0), num_views, rc.views_per_step))
    final, aux = _loss(y, first_views, cfg, rc)
    losses.append(float(final))
    dropped = max(dropped, int(aux["dropped"]))
    info = RefineInfo(
        np.asarray(losses, np.float32),
        taken,
        dropped,
        rc.views_per_step,
        int(cfg.splat.max_intersections),  # pyright: ignore[reportArgumentType] -- fit_capacity above sets the capacity
        compile_s,
        float(np.median(times[1:])) if len(times) > 1 else (times[0] if times else 0.0),
        compile_note,
    )
    return from_unconstrained(y), info


@functools.partial(jax.jit, static_argnames=("cfg", "height", "width"))
def _render_rgb(params, cfg, gaussians, c2w, intrinsics, height, width):
    return render(params, cfg, gaussians, c2w, intrinsics, height, width, ("rgb",)).images["rgb"]


def heldout_psnr(
    params: dict,
    cfg: ModelConfig,
    gaussians: Gaussians,
    target_images: Float[Array, "B T H W 3"],
    target_c2w: Float[Array, "B T 4 4"],
    target_intrinsics: Float[Array, "B T 4"],
) -> float:
    """Mean PSNR (dB, ``metrics.psnr`` of clamped renders) over the T target views and B scenes.

    Renders one target at a time (one compiled shape, memory of one view), as ``evaluate``
    scores: per view, then the mean.
    """
    target_images = jnp.asarray(target_images)
    h, w = target_images.shape[2:4]
    values = []
    for t in range(target_images.shape[1]):
        rgb = _render_rgb(
            params,
            cfg,
            gaussians,
            jnp.asarray(target_c2w)[:, t : t + 1],
            jnp.asarray(target_intrinsics)[:, t : t + 1],
            h,
            w,
        )
        values.append(psnr(rgb, target_images[:, t : t + 1]))
    return float(jnp.mean(jnp.concatenate(values, axis=1)))
