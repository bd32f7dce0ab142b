"""The splatter's entry point: :func:`rasterize` renders Gaussians for one camera in one of
gsplat's render modes (features, SH colour, depth, expected depth), and :func:`fit_capacity`
sizes its intersection buffer from the cameras.

``rasterize`` = projection -> tile binning -> front-to-back composite, jitted with
``height``, ``width``, ``cfg`` and the mode static. Everything is ``jax.vmap``-able (over
cameras, over scenes); ``[S, N]`` opacities render S opacity copies of the same Gaussians
(Long-LRM++'s multi-space partition) sharing one projection and one binning, which is
cheaper than vmapping over the copies.

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
import math
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from jax import lax

from llrmpp_jax.array_typing import Array, ArrayLike, Bool, Float, Int
from llrmpp_jax.splat.binning import SATURATION, bin_gaussians, intersection_counts
from llrmpp_jax.splat.composite import composite
from llrmpp_jax.splat.composite_surfel import DEPTH_MODES
from llrmpp_jax.splat.config import SplatConfig
from llrmpp_jax.splat.projection import camera_is_valid, project_gaussians
from llrmpp_jax.splat.render_surfel import render_surfel_copies, surfel_counts
from llrmpp_jax.splat.sh import MAX_DEGREE, num_sh_bases, sh_colors
from llrmpp_jax.splat.surfel import project_surfels


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
    """A rendered canvas (:func:`rasterize`; a leading S axis with ``[S, N]`` opacities).

    The last three are rendered by ``primitive="2dgs"`` only (None for 3DGS)."""

    features: Float[Array, "H W C"]  # sum_i w_i f_i (+ transmittance * background if one was given)
    transmittance: Float[Array, "H W"]  # final T = prod_i (1 - alpha_i); alpha = 1 - T
    depth: Float[Array, "H W"]  # camera z: sum_i w_i z_i, or over alpha in the "ED" modes
    stats: SplatStats
    normals: Float[Array, "H W 3"] | None = None  # 2DGS: sum_i w_i n_i, camera frame
    median_depth: Float[Array, "H W"] | None = None  # 2DGS: z where T first falls to <= 0.5
    distortion: Float[Array, "H W"] | None = None  # 2DGS: sum_{j<i} 2 w_i w_j (z_i - z_j)


# gsplat's "ED" clamp of the accumulated alpha. A drawn pixel's alpha is at least
# SplatConfig.alpha_min (1/255): any clamp below that gives the same depths.
EXPECTED_DEPTH_MIN_ALPHA = 1e-10


def _expected_depth(
    depth: Float[Array, "*batch H W"], transmittance: Float[Array, "*batch H W"]
) -> Float[Array, "*batch H W"]:
    """gsplat's "ED": accumulated camera z over accumulated alpha (``1 - transmittance``),
    0 where nothing was drawn."""
    alpha = 1.0 - transmittance
    return jnp.where(alpha > 0, depth / jnp.maximum(alpha, EXPECTED_DEPTH_MIN_ALPHA), 0.0)


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
        ok = len(shape) == len(expected) and all(e in ("N", "*") or s == e for s, e in zip(shape, expected))
        if not ok:
            pretty = "(" + ", ".join(str(e) for e in expected) + ")"
            raise ValueError(f"{name} must have shape {pretty}, got {shape}")
        n = shape[expected.index("N")]
        if n_from is None:
            n_from = (name, n, shape)
        elif n != n_from[1]:
            raise ValueError(
                f"{name} has N={n} Gaussians (shape {shape}) but {n_from[0]} has N={n_from[1]} (shape {n_from[2]})"
            )
        if not jnp.issubdtype(x.dtype, jnp.floating):
            raise ValueError(f"{name} must be floating point, got dtype {x.dtype}")
    assert n_from is not None
    if n_from[1] < 1:
        raise ValueError(f"need at least one Gaussian, {n_from[0]} has shape {n_from[2]}")
    return n_from[1]


def _check_values(c2w: ArrayLike, intrinsics: ArrayLike, **arrays: ArrayLike) -> None:
    """Value checks for concrete (non-traced) inputs; under jit the masking rule applies."""
    if any(isinstance(x, jax.core.Tracer) for x in (c2w, intrinsics, *arrays.values())):  # pyright: ignore[reportAttributeAccessIssue] -- jax.core is loaded with jax; Tracer is the type of traced values
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


def _stats(radii, bins, capacity, attr_ok, geo_ok, c2w, intrinsics) -> SplatStats:
    return SplatStats(
        num_visible=jnp.sum(radii > 0, dtype=jnp.int32),
        num_intersections=bins.num_intersections,
        capacity=jnp.asarray(capacity, jnp.int32),
        overflow=bins.overflow,
        num_dropped=bins.num_dropped,
        max_tile_intersections=jnp.max(bins.tile_count),
        num_nonfinite=jnp.sum(~(attr_ok & geo_ok), dtype=jnp.int32),
        invalid_camera=~camera_is_valid(c2w, intrinsics),
    )


def _render_copies(
    means, quats, scales, opacities, features, c2w, intrinsics, height, width, cfg, keep=None, primitive="3dgs"
):
    """Shared core: ``opacities`` is ``[S, N]``; returns an output with a leading S axis.

    ``keep`` (optional ``[N]`` bool) drops more Gaussians, counted as non-finite.
    ``primitive`` is ``"3dgs"`` or ``"2dgs:<depth>"`` (the surfel depth mode).
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
    if primitive != "3dgs":
        capacity = cfg.capacity(n, height, width)
        surf = render_surfel_copies(
            means, quats, scales, opacities, features, c2w, intrinsics, height, width, capacity, cfg,
            primitive.split(":")[1], attr_ok,
        )  # fmt: skip
        stats = _stats(surf.radii, surf.bins, capacity, attr_ok, geo_ok, c2w, intrinsics)
        return SplatOutput(
            surf.features, surf.transmittance, surf.depth, stats, surf.normals, surf.median_depth, surf.distortion
        )

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
    stats = _stats(proj.radii, bins, capacity, attr_ok, geo_ok, c2w, intrinsics)
    return SplatOutput(canvas[..., :f], trans, canvas[..., f], stats)


RENDER_MODES = ("F", "F+ED", "RGB", "RGB+ED", "D", "ED")
PRIMITIVES = ("3dgs", "2dgs")


def _check_primitive(primitive: str, surfel_depth: str | None) -> str:
    """The static primitive key of the core: ``"3dgs"`` or ``"2dgs:<depth>"``."""
    if primitive not in PRIMITIVES:
        raise ValueError(f"primitive must be one of {PRIMITIVES}, got {primitive!r}")
    if primitive == "3dgs":
        if surfel_depth is not None:
            raise ValueError(f"surfel_depth is for primitive '2dgs', got primitive {primitive!r}")
        return primitive
    depth = "center" if surfel_depth is None else surfel_depth
    if depth not in DEPTH_MODES:
        raise ValueError(f"surfel_depth must be one of {DEPTH_MODES}, got {surfel_depth!r}")
    return f"2dgs:{depth}"


def _check_inputs(
    means, quats, scales, opacities, features, c2w, intrinsics, height, width, background, render_mode, sh_degree, kind
) -> int | None:
    """The entry point's checks: ``ValueError`` naming the bad argument. Returns the SH
    degree of an "RGB" mode (None otherwise)."""
    if render_mode not in RENDER_MODES:
        raise ValueError(f"render_mode must be one of {RENDER_MODES}, got {render_mode!r}")
    colour = render_mode.split("+")[0]
    opac_shape = ("N",) if len(_shape(opacities, "opacities")) == 1 else ("*", "N")
    n_scales = 3 if kind == "3dgs" else 2
    if kind != "3dgs" and len(_shape(scales, "scales")) == 2 and _shape(scales, "scales")[1] != 2:
        raise ValueError(
            f"scales must have shape (N, 2) for primitive '2dgs' (two tangent scales of a planar disk), "
            f"got {_shape(scales, 'scales')}"
        )
    per_gaussian = dict(
        means=(means, ("N", 3)),
        quats=(quats, ("N", 4)),
        scales=(scales, ("N", n_scales)),
        opacities=(opacities, opac_shape),
    )
    degree = None
    if colour in ("D", "ED"):
        if features is not None or background is not None:
            raise ValueError(f"render_mode {render_mode!r} renders depth only: pass features=None, background=None")
    elif features is None:
        raise ValueError(f"render_mode {render_mode!r} needs features; depth alone is render_mode 'D' or 'ED'")
    elif colour == "F":
        per_gaussian["features"] = (features, ("N", "*"))  # pyright: ignore[reportArgumentType] -- an axis spec names its axes with str or int
    else:
        m = _shape(features, "features")
        if len(m) != 3 or m[2] != 3:
            raise ValueError(
                f"features must have shape (N, sh, 3) (SH coefficients) in render_mode {render_mode!r}, got {m}"
            )
        degree = round(m[1] ** 0.5) - 1 if sh_degree is None else sh_degree
        if not 0 <= degree <= MAX_DEGREE or num_sh_bases(degree) > m[1]:
            raise ValueError(
                f"sh_degree {degree} (0..{MAX_DEGREE}) needs {num_sh_bases(degree)} coefficients; "
                f"features has shape {m}"
            )
        if sh_degree is None and num_sh_bases(degree) != m[1]:
            raise ValueError(f"features has sh={m[1]} coefficients, not a square; pass sh_degree")
        per_gaussian["features"] = (features, ("N", "*", 3))  # pyright: ignore[reportArgumentType] -- as above
    if colour != "RGB" and sh_degree is not None:
        raise ValueError(f"sh_degree is for the 'RGB' render modes, got render_mode {render_mode!r}")
    if background is not None:
        channels = 3 if colour == "RGB" else _shape(features, "features")[-1]
        if _shape(background, "background") != (channels,):
            raise ValueError(f"background must have shape ({channels},), got {_shape(background, 'background')}")
    _check_shapes(height, width, c2w, intrinsics, **per_gaussian)
    _check_values(c2w, intrinsics, **{name: x for name, (x, _) in per_gaussian.items()})
    return degree


def rasterize(
    means: Float[ArrayLike, "N 3"],
    quats: Float[ArrayLike, "N 4"],
    scales: Float[ArrayLike, "N 3"] | Float[ArrayLike, "N 2"],
    opacities: Float[ArrayLike, " N"] | Float[ArrayLike, "S N"],
    features: Float[ArrayLike, "N F"] | Float[ArrayLike, "N sh 3"] | None,
    c2w: Float[ArrayLike, "4 4"],
    intrinsics: Float[ArrayLike, " 4"],
    height: int,
    width: int,
    cfg: SplatConfig = SplatConfig(),
    *,
    render_mode: str = "F",
    background: Float[ArrayLike, " C"] | None = None,
    sh_degree: int | None = None,
    primitive: str = "3dgs",
    surfel_depth: str | None = None,
) -> SplatOutput:
    """Render N Gaussians for one camera (gsplat's ``rasterization`` with its render modes).

    ``means`` world positions, ``quats`` (w, x, y, z) (normalised inside), ``scales``
    linear (not log), ``opacities`` in [0, 1]; ``c2w`` OpenCV camera-to-world,
    ``intrinsics`` (fx, fy, cx, cy) in pixels of the ``height x width`` canvas.
    ``render_mode`` says what ``features`` holds and what comes out:

    * ``"F"``: ``features [N, F]`` (any width F); ``out.features [H, W, F]`` = ``sum_i w_i f_i``.
    * ``"RGB"``: ``features [N, sh, 3]`` SH coefficients (Long-LRM's colour mode; degree
      ``sh_degree``, default ``sqrt(sh) - 1``, extra coefficients ignored); each Gaussian's
      colour is ``max(SH(mean - camera centre) + 0.5, 0)`` (gsplat) and
      ``out.features [H, W, 3]`` their composite.
    * ``"D"``: ``features=None``, depth only (``out.features`` has 0 channels).
    * ``"ED"`` or a ``"+ED"`` suffix: ``out.depth`` is the expected camera z
      ``sum_i w_i z_i / (1 - T)`` (0 where nothing was drawn) instead of the accumulated
      ``sum_i w_i z_i``.

    ``background`` (``[F]`` or ``[3]``; "F" and "RGB" modes) is composited under the
    canvas: ``features + transmittance * background``; None adds none. ``opacities`` of
    shape ``[S, N]`` render S copies of the Gaussians that differ only in opacity
    (Long-LRM++'s partition copies), sharing one projection and one binning: every output
    but ``stats`` then has a leading S axis, and a Gaussian whose opacity is non-finite in
    any copy is dropped from all (under jit).

    ``primitive="2dgs"`` renders 2D Gaussians (surfels, 2DGS; :mod:`.surfel` and
    :mod:`.composite_surfel` state the rules): ``scales [N, 2]`` are the two tangent
    scales, the normal is R(q)'s third column; ``out.normals`` (camera frame, alpha
    weighted), ``out.median_depth`` and ``out.distortion`` are rendered too. Its depth
    ``surfel_depth`` is ``"center"`` (default: each surfel's centre z, as gsplat's
    ``rasterization_2dgs`` composites, and what Long-LRM's gsplat-based 2DGS baseline
    rendered) or ``"intersection"`` (the ray-splat intersection's z, as the 2DGS paper's
    rasterizer: per-pixel depth on a tilted surfel); median depth and distortion use the
    same depth.

    Computes in float32 (float64 if ``means`` is float64). Differentiable w.r.t. means,
    quats, scales, opacities and features; ``jax.vmap``-able over cameras and scenes.
    Called outside ``jit`` with ``cfg.max_intersections`` unset, the buffer is sized from
    this scene (:func:`fit_capacity`).
    """
    key = _check_primitive(primitive, surfel_depth)
    scene = (means, quats, scales, opacities, features, c2w, intrinsics)
    degree = _check_inputs(*scene, height, width, background, render_mode, sh_degree, primitive)
    if not any(isinstance(x, jax.core.Tracer) for x in (means, quats, scales, opacities, c2w, intrinsics)):  # pyright: ignore[reportAttributeAccessIssue] -- jax.core is loaded with jax; Tracer is the type of traced values
        cfg = fit_capacity(means, quats, scales, opacities, c2w, intrinsics, height, width, cfg, primitive=primitive)
    return _rasterize_jit(*scene, background, height, width, cfg, render_mode, degree, key)


def _rasterize(
    means, quats, scales, opacities, features, c2w, intrinsics, background, height, width, cfg, mode, degree, key
):
    dtype = _compute_dtype(means)
    copies = opacities.ndim == 2
    keep = None
    if degree is not None:
        # Sanitise before evaluating SH so a bad Gaussian cannot put NaN into gradients; the
        # renderer then drops it (keep=False) and counts it as non-finite.
        keep = jnp.all(jnp.isfinite(features), axis=(1, 2))
        coeffs = jnp.where(keep[:, None, None], features.astype(dtype), 0.0)
        safe_means = jnp.where(jnp.isfinite(means), means, 0.0).astype(dtype)
        features = sh_colors(safe_means, coeffs, c2w.astype(dtype), degree)
    elif features is None:
        features = jnp.zeros((means.shape[0], 0), dtype)
    out = _render_copies(
        means,
        quats,
        scales,
        opacities if copies else opacities[None, :],
        features,
        c2w,
        intrinsics,
        height,
        width,
        cfg,
        keep=keep,
        primitive=key,
    )
    if not copies:
        out = jax.tree.map(lambda x: x[0], out._replace(stats=None))._replace(stats=out.stats)
    canvas, depth = out.features, out.depth
    if background is not None:
        under = background.astype(dtype).reshape((1,) * (canvas.ndim - 1) + (-1,))
        canvas = canvas + out.transmittance[..., None] * under
    if mode.endswith("ED"):
        depth = _expected_depth(depth, out.transmittance)
    return out._replace(features=canvas, depth=depth)


_rasterize_jit = jax.jit(_rasterize, static_argnames=("height", "width", "cfg", "mode", "degree", "key"))


def fit_capacity(
    means: Float[ArrayLike, "*batch N 3"],
    quats: Float[ArrayLike, "*batch N 4"],
    scales: Float[ArrayLike, "*batch N 3"] | Float[ArrayLike, "*batch N 2"],
    opacities: Float[ArrayLike, "*batch N"] | Float[ArrayLike, "*batch S N"],
    c2w: Float[ArrayLike, "... 4 4"],
    intrinsics: Float[ArrayLike, "... 4"],
    height: int,
    width: int,
    cfg: SplatConfig = SplatConfig(),
    *,
    headroom: float = 1.0,
    minimum: int = 0,
    primitive: str = "3dgs",
) -> SplatConfig:
    """``cfg`` with its capacity (``max_intersections``) sized for rendering these Gaussians
    at these cameras on ``height x width`` canvases.

    The capacity is ``headroom`` x the most (Gaussian, compositor block) slots any camera's
    render fills (the exact count, opacity-trimmed as the render bins; with ``[S, N]``
    copies, of the most opaque copy), rounded up to the next size of the form ``m 2^e``
    with ``m`` in 8..15 (wastes under 1/8; similar scenes share one compiled program), and
    at least ``minimum``. One scene (``means [N, 3]``, cameras ``[T, 4, 4]`` / ``[T, 4]``
    or a single ``[4, 4]`` / ``[4]``) or B (a leading B axis on all). A ``cfg`` that sets
    the capacity keeps it. Eager (returns a static config); the count is a projection per
    camera, no sort and no composite. ``primitive="2dgs"`` counts surfels (``scales [N, 2]``).
    """
    if cfg.max_intersections is not None:
        return cfg
    means = jnp.asarray(means)
    lead = means.ndim - 2  # 0: one scene, 1: B scenes
    arrays = [jnp.asarray(x) for x in (means, quats, scales, opacities)]
    scenes = [x if lead else x[None] for x in arrays]
    cams = [jnp.asarray(x) for x in (c2w, intrinsics)]
    b = scenes[0].shape[0]
    cams = [x.reshape(b, -1, *x.shape[x.ndim - tail :]) for x, tail in zip(cams, (2, 1))]

    def one(x, lead):  # a zero-size-in-memory stand-in of one scene's / camera's array
        return np.broadcast_to(np.zeros((), x.dtype), x.shape[lead:])

    _check_shapes(
        height,
        width,
        one(cams[0], 2),
        one(cams[1], 2),
        **{
            name: (one(x, 1), shape)
            for name, x, shape in zip(
                ("means", "quats", "scales", "opacities"),
                scenes,
                (
                    ("N", 3),
                    ("N", 4),
                    ("N", 3 if primitive == "3dgs" else 2),
                    ("N",) if scenes[3].ndim == 2 else ("*", "N"),
                ),
            )
        },
    )
    _check_primitive(primitive, None)
    needed = int(jnp.max(_count_jit(*scenes, *cams, height, width, cfg, primitive)))
    return dataclasses.replace(cfg, max_intersections=max(_round_capacity(math.ceil(headroom * needed)), minimum))


def _count(means, quats, scales, opacities, c2w, intrinsics, height, width, cfg, primitive="3dgs"):
    """Slots one scene's render fills at one camera (saturating at 2**30 - 1)."""
    dtype = _compute_dtype(means)
    means, quats, scales, c2w, intrinsics = (
        jnp.asarray(x).astype(dtype) for x in (means, quats, scales, c2w, intrinsics)
    )
    opacities = jnp.max(opacities.reshape(-1, opacities.shape[-1]), axis=0)  # the most opaque copy
    keep = jnp.isfinite(opacities)
    opacities = jnp.where(keep, opacities, 0.0).astype(dtype)
    if primitive == "3dgs":
        proj = project_gaussians(means, quats, scales, c2w, intrinsics, height, width, cfg, keep=keep)
        counts = intersection_counts(proj, height, width, cfg, opacities)
    else:
        proj = project_surfels(means, quats, scales, opacities, c2w, intrinsics, height, width, cfg, keep=keep)
        counts = surfel_counts(proj, height, width, cfg)
    return lax.reduce(counts, jnp.int32(0), lambda a, b: jnp.minimum(a + b, SATURATION), (0,))


def _count_views(means, quats, scales, opacities, c2w, intrinsics, height, width, cfg, primitive):
    """``[B, T]`` slots of B scenes at each of their T cameras."""
    per_camera = jax.vmap(_count, (None, None, None, None, 0, 0, None, None, None, None))
    return jax.vmap(per_camera, (0, 0, 0, 0, 0, 0, None, None, None, None))(
        means, quats, scales, opacities, c2w, intrinsics, height, width, cfg, primitive
    )


_count_jit = jax.jit(_count_views, static_argnames=("height", "width", "cfg", "primitive"))


def _round_capacity(needed: int) -> int:
    """The next size ``>= needed`` of the form ``m 2^e`` with ``m`` in 8..15 (any size below 8)."""
    needed = max(int(needed), 1)
    e = max(needed.bit_length() - 4, 0)
    return min(-(-needed // (1 << e)) << e, SATURATION)
