"""Public entry points: render feature Gaussians (or SH colour Gaussians) for one camera.

``render_features`` = projection -> tile binning -> front-to-back composite, jitted with
``height``, ``width`` and ``cfg`` static. Everything is ``jax.vmap``-able (over cameras,
over scenes); ``render_feature_copies`` renders S opacity copies of the same Gaussians
(Long-LRM++'s multi-space partition) sharing one projection and one binning, which is
cheaper than vmapping ``render_features`` over the copies.

Bad input:

* shapes are checked before tracing: a ``ValueError`` names the argument, its shape and
  the expected one (or both arguments when their N disagree);
* called eagerly with concrete arrays, non-finite means / quaternions / scales /
  opacities / features, or a camera with non-finite entries or ``fx <= 0`` / ``fy <= 0``,
  raise a ``ValueError``;
* under ``jit`` / ``vmap`` (values unknown) the masking rule applies instead: a Gaussian
  with any non-finite input is dropped (never rendered, zero gradient; counted in
  ``stats.num_nonfinite``), and an invalid camera renders nothing (``stats.invalid_camera``;
  features and depth 0, transmittance 1).
"""

from __future__ import annotations

import dataclasses
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from jax import lax

from llrmpp_jax.array_typing import Array, ArrayLike, Bool, Float, Int
from llrmpp_jax.splat.binning import SATURATION, bin_gaussians, intersection_counts
from llrmpp_jax.splat.composite import composite
from llrmpp_jax.splat.config import SplatConfig
from llrmpp_jax.splat.projection import camera_is_valid, project_gaussians
from llrmpp_jax.splat.sh import MAX_DEGREE, num_sh_bases, sh_colors


class SplatStats(NamedTuple):
    """Counts of one render; check ``overflow`` (never silently ignored)."""

    num_visible: Int[Array, ""]  # Gaussians that survived culling
    num_intersections: Int[Array, ""]  # (Gaussian, tile) pairs needed (saturates at 2**30 - 1)
    capacity: Int[Array, ""]  # size of the intersection buffer (static)
    overflow: Bool[Array, ""]  # num_intersections > capacity
    num_dropped: Int[Array, ""]  # entries lost to overflow (the farthest ones)
    max_tile_intersections: Int[Array, ""]  # longest per-tile list (sets the loop length)
    num_nonfinite: Int[Array, ""]  # Gaussians dropped for non-finite inputs
    invalid_camera: Bool[Array, ""]  # camera non-finite or with fx <= 0 / fy <= 0


class SplatOutput(NamedTuple):
    """A rendered canvas. Compose a background b as ``features + transmittance[..., None] * b``."""

    features: Float[Array, "H W F"]  # sum_i w_i f_i, no background
    transmittance: Float[Array, "H W"]  # final T = prod_i (1 - alpha_i); alpha = 1 - T
    depth: Float[Array, "H W"]  # sum_i w_i z_i, camera z, unnormalised (divide by 1 - T)
    stats: SplatStats


# gsplat's "ED" clamp of the accumulated alpha. A drawn pixel's alpha is at least
# SplatConfig.alpha_min (1/255): any clamp below that gives the same depths.
EXPECTED_DEPTH_MIN_ALPHA = 1e-10


def expected_depth(out: SplatOutput) -> Float[Array, "*batch H W"]:
    """gsplat's "ED" render mode: accumulated camera z over accumulated alpha
    (``out.depth / (1 - out.transmittance)``), 0 where nothing was drawn. The one
    definition used by the model's depth, the depth loss, ``llrmpp render --depth`` and
    the viewer."""
    alpha = 1.0 - out.transmittance
    return jnp.where(alpha > 0, out.depth / jnp.maximum(alpha, EXPECTED_DEPTH_MIN_ALPHA), 0.0)


def _compute_dtype(means: ArrayLike) -> jnp.dtype:
    return jnp.dtype(jnp.float64) if means.dtype == jnp.float64 else jnp.dtype(jnp.float32)


def _shape(x: object, name: str) -> tuple[int, ...]:
    shape = getattr(x, "shape", None)
    if shape is None:
        raise ValueError(f"{name} must be an array, got {type(x).__name__}")
    return tuple(shape)


def _check_shapes(
    height: int,
    width: int,
    c2w: ArrayLike,
    intrinsics: ArrayLike,
    **per_gaussian: tuple[ArrayLike, tuple[int | str, ...]],
) -> int:
    """Check shapes (``"N"`` marks the Gaussian axis, ``"*"`` any size); return N."""
    if not (isinstance(height, (int, np.integer)) and isinstance(width, (int, np.integer))):
        raise ValueError(f"height and width must be Python ints, got {height!r}, {width!r}")
    if height < 1 or width < 1:
        raise ValueError(f"height and width must be >= 1, got height={height}, width={width}")
    if _shape(c2w, "c2w") != (4, 4):
        raise ValueError(f"c2w must have shape (4, 4), got {_shape(c2w, 'c2w')}")
    if _shape(intrinsics, "intrinsics") != (4,):
        raise ValueError(f"intrinsics (fx, fy, cx, cy) must have shape (4,), got {_shape(intrinsics, 'intrinsics')}")
    n_from: tuple[str, int, tuple[int, ...]] | None = None
    for name, (x, expected) in per_gaussian.items():
        shape = _shape(x, name)
        ok = len(shape) == len(expected) and all(
            e in ("N", "*") or s == e for s, e in zip(shape, expected)
        )
        if not ok:
            pretty = "(" + ", ".join(str(e) for e in expected) + ")"
            raise ValueError(f"{name} must have shape {pretty}, got {shape}")
        n = shape[expected.index("N")]
        if n_from is None:
            n_from = (name, n, shape)
        elif n != n_from[1]:
            raise ValueError(
                f"{name} has N={n} Gaussians (shape {shape}) but {n_from[0]} has "
                f"N={n_from[1]} (shape {n_from[2]})"
            )
        if not jnp.issubdtype(x.dtype, jnp.floating):
            raise ValueError(f"{name} must be floating point, got dtype {x.dtype}")
    assert n_from is not None
    if n_from[1] < 1:
        raise ValueError(f"need at least one Gaussian, {n_from[0]} has shape {n_from[2]}")
    return n_from[1]


def _check_values(c2w: ArrayLike, intrinsics: ArrayLike, **arrays: ArrayLike) -> None:
    """Value checks for concrete (non-traced) inputs; under jit the masking rule applies."""
    if any(isinstance(x, jax.core.Tracer) for x in (c2w, intrinsics, *arrays.values())):
        return
    for name, x in arrays.items():
        bad = ~np.isfinite(np.asarray(x))
        if bad.any():
            first = np.argwhere(bad)[0].tolist()
            raise ValueError(f"{name} has {int(bad.sum())} non-finite entries (first at index {first})")
    k = np.asarray(intrinsics)
    if not (np.isfinite(k).all() and k[0] > 0 and k[1] > 0):
        raise ValueError(f"intrinsics (fx, fy, cx, cy) must be finite with fx, fy > 0, got {k.tolist()}")
    if not np.isfinite(np.asarray(c2w)).all():
        raise ValueError("c2w has non-finite entries")


def _render_copies(
    means, quats, scales, opacities, features, c2w, intrinsics, height, width, cfg, keep=None
):
    """Shared core: ``opacities`` is ``[S, N]``; returns an output with a leading S axis.

    ``keep`` (optional ``[N]`` bool) drops more Gaussians, counted as non-finite.
    """
    dtype = _compute_dtype(means)
    means, quats, scales, opacities, features, c2w, intrinsics = (
        jnp.asarray(x).astype(dtype) for x in (means, quats, scales, opacities, features, c2w, intrinsics)
    )
    n, f = features.shape
    attr_ok = jnp.all(jnp.isfinite(opacities), axis=0) & jnp.all(jnp.isfinite(features), axis=-1)
    if keep is not None:
        attr_ok = attr_ok & keep
    geo_ok = (
        jnp.all(jnp.isfinite(means), axis=-1)
        & jnp.all(jnp.isfinite(quats), axis=-1)
        & jnp.all(jnp.isfinite(scales), axis=-1)
    )
    opacities = jnp.where(attr_ok[None, :], opacities, 0.0)
    features = jnp.where(attr_ok[:, None], features, 0.0)

    with jax.named_scope("splat_project"):
        proj = project_gaussians(means, quats, scales, c2w, intrinsics, height, width, cfg, keep=attr_ok)
    capacity = cfg.capacity(n, height, width)
    # Boxes trimmed to where the most opaque copy can be drawn: less work, same output.
    with jax.named_scope("splat_bin"):
        bins = bin_gaussians(proj, height, width, capacity, cfg, opacities=jnp.max(opacities, axis=0))
    # Depth rides along as one more feature channel: one composite gives both.
    feats_z = jnp.concatenate([features, proj.depths[:, None]], axis=-1)

    @jax.named_scope("splat_composite")
    def one(op):
        return composite(proj.means2d, proj.quad_form, op, feats_z, bins, height, width, cfg)

    canvas, trans = jax.vmap(one)(opacities)
    stats = SplatStats(
        num_visible=jnp.sum(proj.radii > 0, dtype=jnp.int32),
        num_intersections=bins.num_intersections,
        capacity=jnp.asarray(capacity, jnp.int32),
        overflow=bins.overflow,
        num_dropped=bins.num_dropped,
        max_tile_intersections=jnp.max(bins.tile_count),
        num_nonfinite=jnp.sum(~(attr_ok & geo_ok), dtype=jnp.int32),
        invalid_camera=~camera_is_valid(c2w, intrinsics),
    )
    return SplatOutput(canvas[..., :f], trans, canvas[..., f], stats)


_render_copies_jit = jax.jit(_render_copies, static_argnames=("height", "width", "cfg"))


def render_feature_copies(
    means: Float[ArrayLike, "N 3"],
    quats: Float[ArrayLike, "N 4"],
    scales: Float[ArrayLike, "N 3"],
    opacities: Float[ArrayLike, "S N"],
    features: Float[ArrayLike, "N F"],
    c2w: Float[ArrayLike, "4 4"],
    intrinsics: Float[ArrayLike, "4"],
    height: int,
    width: int,
    cfg: SplatConfig = SplatConfig(),
) -> SplatOutput:
    """Render S copies of the same Gaussians that differ only in opacity.

    Returns features ``[S, H, W, F]``, transmittance and depth ``[S, H, W]``; ``stats``
    (one projection and binning for all copies) has no S axis. A Gaussian whose opacity is
    non-finite in any copy is dropped from all copies (under jit).
    """
    _check_shapes(
        height, width, c2w, intrinsics,
        means=(means, ("N", 3)), quats=(quats, ("N", 4)), scales=(scales, ("N", 3)),
        opacities=(opacities, ("*", "N")), features=(features, ("N", "*")),
    )
    _check_values(c2w, intrinsics, means=means, quats=quats, scales=scales, opacities=opacities, features=features)
    cfg = _fit_capacity(cfg, means, quats, scales, opacities, c2w, intrinsics, height, width)
    return _render_copies_jit(means, quats, scales, opacities, features, c2w, intrinsics, height, width, cfg)


def render_features(
    means: Float[ArrayLike, "N 3"],
    quats: Float[ArrayLike, "N 4"],
    scales: Float[ArrayLike, "N 3"],
    opacities: Float[ArrayLike, "N"],
    features: Float[ArrayLike, "N F"],
    c2w: Float[ArrayLike, "4 4"],
    intrinsics: Float[ArrayLike, "4"],
    height: int,
    width: int,
    cfg: SplatConfig = SplatConfig(),
) -> SplatOutput:
    """Render N feature Gaussians to an ``[height, width, F]`` canvas for one camera.

    ``means`` world positions, ``quats`` (w, x, y, z) (normalised inside), ``scales``
    linear (not log), ``opacities`` in [0, 1], ``features`` any width F; ``c2w`` OpenCV
    camera-to-world, ``intrinsics`` (fx, fy, cx, cy) in pixels of this canvas. Computes in
    float32 (float64 if ``means`` is float64). Differentiable w.r.t. means, quats, scales,
    opacities and features.
    """
    _check_shapes(
        height, width, c2w, intrinsics,
        means=(means, ("N", 3)), quats=(quats, ("N", 4)), scales=(scales, ("N", 3)),
        opacities=(opacities, ("N",)), features=(features, ("N", "*")),
    )
    _check_values(c2w, intrinsics, means=means, quats=quats, scales=scales, opacities=opacities, features=features)
    cfg = _fit_capacity(cfg, means, quats, scales, opacities, c2w, intrinsics, height, width)
    out = _render_copies_jit(
        means, quats, scales, opacities[None, :], features, c2w, intrinsics, height, width, cfg
    )
    return SplatOutput(out.features[0], out.transmittance[0], out.depth[0], out.stats)


def render_sh(
    means: Float[ArrayLike, "N 3"],
    quats: Float[ArrayLike, "N 4"],
    scales: Float[ArrayLike, "N 3"],
    opacities: Float[ArrayLike, "N"],
    sh_coeffs: Float[ArrayLike, "N sh 3"],
    c2w: Float[ArrayLike, "4 4"],
    intrinsics: Float[ArrayLike, "4"],
    height: int,
    width: int,
    cfg: SplatConfig = SplatConfig(),
    background: Float[ArrayLike, "3"] | None = None,
    *,
    sh_degree: int | None = None,
) -> tuple[Float[Array, "H W 3"], SplatOutput]:
    """Long-LRM colour mode: SH colours seen from the camera, splatted over a background.

    Colour of a Gaussian = ``max(SH(mean - camera centre) + 0.5, 0)`` (gsplat);
    ``rgb = features + transmittance * background`` (default white). ``sh_degree``
    defaults to ``sqrt(sh) - 1``; with fewer, the extra coefficients are ignored.
    Returns ``(rgb [H, W, 3], output)`` where ``output.features`` has no background.
    """
    m = _shape(sh_coeffs, "sh_coeffs")
    if len(m) != 3 or m[2] != 3:
        raise ValueError(f"sh_coeffs must have shape (N, sh, 3), got {m}")
    degree = round(m[1] ** 0.5) - 1 if sh_degree is None else sh_degree
    if not 0 <= degree <= MAX_DEGREE or num_sh_bases(degree) > m[1]:
        raise ValueError(
            f"sh_degree {degree} (0..{MAX_DEGREE}) needs {num_sh_bases(degree)} coefficients; "
            f"sh_coeffs has shape {m}"
        )
    if sh_degree is None and num_sh_bases(degree) != m[1]:
        raise ValueError(f"sh_coeffs has sh={m[1]} coefficients, not a square; pass sh_degree")
    background = jnp.ones((3,), jnp.float32) if background is None else background
    if _shape(background, "background") != (3,):
        raise ValueError(f"background must have shape (3,), got {_shape(background, 'background')}")
    _check_shapes(
        height, width, c2w, intrinsics,
        means=(means, ("N", 3)), quats=(quats, ("N", 4)), scales=(scales, ("N", 3)),
        opacities=(opacities, ("N",)), sh_coeffs=(sh_coeffs, ("N", "*", 3)),
    )
    _check_values(c2w, intrinsics, means=means, quats=quats, scales=scales, opacities=opacities, sh_coeffs=sh_coeffs)
    cfg = _fit_capacity(cfg, means, quats, scales, opacities, c2w, intrinsics, height, width)
    return _render_sh_jit(
        means, quats, scales, opacities, sh_coeffs, c2w, intrinsics, background, height, width, cfg, degree
    )


def _render_sh(means, quats, scales, opacities, sh_coeffs, c2w, intrinsics, background, height, width, cfg, degree):
    dtype = _compute_dtype(means)
    # Sanitise before evaluating SH so a bad Gaussian cannot put NaN into gradients; the
    # renderer then drops it (keep=False) and counts it as non-finite.
    coeff_ok = jnp.all(jnp.isfinite(sh_coeffs), axis=(1, 2))
    coeffs = jnp.where(coeff_ok[:, None, None], sh_coeffs.astype(dtype), 0.0)
    safe_means = jnp.where(jnp.isfinite(means), means, 0.0).astype(dtype)
    colors = sh_colors(safe_means, coeffs, c2w.astype(dtype), degree)
    out = _render_copies(
        means, quats, scales, opacities[None, :], colors, c2w, intrinsics, height, width, cfg,
        keep=coeff_ok,
    )
    out = SplatOutput(out.features[0], out.transmittance[0], out.depth[0], out.stats)
    rgb = out.features + out.transmittance[:, :, None] * background.astype(dtype)[None, None, :]
    return rgb, out


_render_sh_jit = jax.jit(_render_sh, static_argnames=("height", "width", "cfg", "degree"))


def count_intersections(
    means: Float[ArrayLike, "N 3"],
    quats: Float[ArrayLike, "N 4"],
    scales: Float[ArrayLike, "N 3"],
    c2w: Float[ArrayLike, "4 4"],
    intrinsics: Float[ArrayLike, "4"],
    height: int,
    width: int,
    cfg: SplatConfig = SplatConfig(),
    opacities: Float[ArrayLike, "N"] | Float[ArrayLike, "S N"] | None = None,
) -> Int[Array, ""]:
    """(Gaussian, compositor block) pairs a render of this scene needs: size
    ``max_intersections`` by it.

    With ``opacities`` (``[N]``, or ``[S, N]`` for the copies of
    :func:`render_feature_copies`) the exact number a render fills; without, an upper bound
    that also counts the blocks where a Gaussian is too faint to be drawn
    (:func:`~llrmpp_jax.splat.binning.screen_extents`). Saturates at 2**30 - 1. Cheap
    (projection only, no sort, no composite).
    """
    _check_shapes(
        height, width, c2w, intrinsics,
        means=(means, ("N", 3)), quats=(quats, ("N", 4)), scales=(scales, ("N", 3)),
    )
    if opacities is not None:
        opacities = jnp.asarray(opacities)
        opacities = jnp.max(opacities.reshape(-1, opacities.shape[-1]), axis=0)
    return _count_jit(means, quats, scales, opacities, c2w, intrinsics, height, width, cfg)


def _count(means, quats, scales, opacities, c2w, intrinsics, height, width, cfg):
    dtype = _compute_dtype(means)
    means, quats, scales, c2w, intrinsics = (
        jnp.asarray(x).astype(dtype) for x in (means, quats, scales, c2w, intrinsics)
    )
    keep = None
    if opacities is not None:
        keep = jnp.isfinite(opacities)
        opacities = jnp.where(keep, opacities, 0.0).astype(dtype)
    proj = project_gaussians(means, quats, scales, c2w, intrinsics, height, width, cfg, keep=keep)
    counts = intersection_counts(proj, height, width, cfg, opacities)
    return lax.reduce(counts, jnp.int32(0), lambda a, b: jnp.minimum(a + b, SATURATION), (0,))


_count_jit = jax.jit(_count, static_argnames=("height", "width", "cfg"))


def fitted_capacity(needed: int) -> int:
    """Buffer size for a scene that needs ``needed`` slots: the next size of the form
    ``m 2^e`` with ``m`` in 8..15, so it wastes under 1/8 and renders of similar scenes share
    one compiled program."""
    needed = max(int(needed), 1)
    e = max(needed.bit_length() - 4, 0)
    return min(-(-needed // (1 << e)) << e, SATURATION)


def _fit_capacity(cfg: SplatConfig, means, quats, scales, opacities, c2w, intrinsics, height, width) -> SplatConfig:
    """``cfg`` with ``max_intersections`` fitted to this scene when it is unset and the
    inputs are concrete (called outside ``jit``); under a trace, ``cfg`` as it is."""
    if cfg.max_intersections is not None or any(
        isinstance(x, jax.core.Tracer) for x in (means, quats, scales, opacities, c2w, intrinsics)
    ):
        return cfg
    needed = int(count_intersections(means, quats, scales, c2w, intrinsics, height, width, cfg, opacities))
    return dataclasses.replace(cfg, max_intersections=fitted_capacity(needed))
