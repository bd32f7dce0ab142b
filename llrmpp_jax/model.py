"""Long-LRM++: images + cameras -> Gaussians -> RGB or depth at any target camera.

The pure API (``cfg`` is a static :class:`~llrmpp_jax.config.ModelConfig`):

* :func:`init_params` -- parameters for ``V`` input views of ``H x W``.
* :func:`reconstruct` -- ``(params, images, c2w, intrinsics) -> Gaussians`` (paper §3.1-3.2).
* :func:`render` -- ``(params, gaussians, target cameras) -> RenderOutput`` (§3.2-3.3):
  feature mode splats the S partition copies to ``(H/r, W/r)`` canvases and decodes them;
  colour mode (Long-LRM) splats SH colours directly over ``cfg.background``, and its depth
  is the expected camera z, ``sum_i w_i z_i / sum_i w_i`` (the accumulated z normalised
  by the accumulated alpha, gsplat's "ED" render mode), so the paper's depth losses train
  it like the feature model's depth head: the colour-Gaussian depth rows of Tables 2 and 7.
  With ``head.primitive="2dgs"`` the colour Gaussians are 2D (two scales) and splatted by the
  2DGS splatter (``splat.rasterize(..., primitive="2dgs")``), the same expected depth of
  their ``head.surfel_depth`` (Table 7's Long-LRM 2DGS row).
  (Long-LRM's own depth term supervises its Gaussian centres instead, facts §2.2.)
* :func:`partition_logits` -- feature mode: the S partition logits of each Gaussian.

Colour-mode configs with ``head.prune_ratio > 0`` (Long-LRM's stage 3) have their Gaussians
pruned between the two calls by :func:`llrmpp_jax.pruning.prune_gaussians`; the trainer
and the evaluator do it (``reconstruct`` returns every Gaussian).

Cameras are OpenCV c2w ``[..., 4, 4]`` and pixel intrinsics ``[..., 4]`` = (fx, fy, cx, cy),
in the normalised scene frame (see ``geometry.normalize_scene``).
"""

from __future__ import annotations

import dataclasses
from typing import NamedTuple

import flax.linen as nn
import jax
import jax.numpy as jnp

from llrmpp_jax import splat
from llrmpp_jax.array_typing import Array, ArrayLike, Float, KeyArray
from llrmpp_jax.config import ModelConfig
from llrmpp_jax.decoder import TargetDecoder, partition_opacities
from llrmpp_jax.errors import UserError
from llrmpp_jax.gaussians import GaussianHead, Gaussians
from llrmpp_jax.geometry import pixel_rays, plucker
from llrmpp_jax.nn.backbone import Backbone


class RenderOutput(NamedTuple):
    images: dict[str, Float[Array, "B T H W C"]]  # "rgb" [.., 3] and/or "depth" [.., 1]
    dropped: Array  # int32 [B]: Gaussian-tile intersections dropped by the splatter's capacity (0 = exact)


def input_features(
    images: Float[ArrayLike, "B V H W 3"], c2w: Float[ArrayLike, "B V 4 4"], intrinsics: Float[ArrayLike, "B V 4"]
) -> Float[Array, "B V H W 9"]:
    """Per-pixel ``[rgb*2-1, o x d, d]`` (Long-LRM / LVSM order; d through pixel centres)."""
    h, w = images.shape[2:4]
    o, d = pixel_rays(c2w, intrinsics, h, w)
    return jnp.concatenate([images * 2.0 - 1.0, plucker(o, d)], axis=-1)


def append_target_rays(
    canvas: Float[Array, "B T S Hc Wc F"],
    c2w: Float[ArrayLike, "B T 4 4"],
    intrinsics: Float[ArrayLike, "B T 4"],
    canvas_ratio: int,
) -> Float[Array, "B T S Hc Wc F+6"]:
    """The decoder's input: each canvas with its target's Plücker rays ``[o x d, d]`` through
    the canvas pixel centres (image intrinsics scaled down by ``canvas_ratio``), paper §3.2."""
    b, t, s, hc, wc, _ = canvas.shape
    rays = plucker(*pixel_rays(c2w, intrinsics / canvas_ratio, hc, wc))  # [B, T, hc, wc, 6]
    rays = jnp.broadcast_to(rays[:, :, None], (b, t, s, hc, wc, 6)).astype(canvas.dtype)
    return jnp.concatenate([canvas, rays], axis=-1)


def _check_views(images, c2w, intrinsics) -> None:
    if images.ndim != 5 or images.shape[-1] != 3:
        raise ValueError(f"images must be [B, V, H, W, 3], got shape {images.shape}")
    b, v = images.shape[:2]
    if c2w.shape != (b, v, 4, 4):
        raise ValueError(f"c2w must be [B, V, 4, 4] = {(b, v, 4, 4)} to match images, got {c2w.shape}")
    if intrinsics.shape != (b, v, 4):
        raise ValueError(f"intrinsics must be [B, V, 4] = {(b, v, 4)} to match images, got {intrinsics.shape}")


class LongLRMPP(nn.Module):
    """Parameter holder; the maths lives in the pure functions of each submodule."""

    cfg: ModelConfig

    def setup(self) -> None:
        cfg = self.cfg
        self.backbone = Backbone(cfg.backbone, cfg.patch_size)
        self.head = GaussianHead(cfg.head, cfg.token_stride)
        if cfg.head.mode == "feature":
            self.partition = nn.Dense(cfg.decoder.partitions, use_bias=False, kernel_init=nn.initializers.normal(0.02))
            self.decoder = TargetDecoder(cfg.decoder)

    def reconstruct(self, images, c2w, intrinsics) -> Gaussians:
        with jax.named_scope("backbone"):  # phases for llrmpp_jax.profiling
            out = self.backbone(input_features(images, c2w, intrinsics))
        with jax.named_scope("gaussian_head"):
            return self.head(out.tokens, out.grid, c2w, intrinsics)

    def render(
        self, gaussians: Gaussians, c2w, intrinsics, height: int, width: int, outputs: tuple[str, ...]
    ) -> RenderOutput:
        cfg = self.cfg
        per_target = lambda f: jax.vmap(jax.vmap(f, (None, 0, 0)), (0, 0, 0))  # noqa: E731  over B, T
        if cfg.head.mode == "color":
            if not outputs or set(outputs) - {"rgb", "depth"}:
                raise ValueError(f"colour mode renders 'rgb' and/or 'depth', asked for {outputs}")
            bg = jnp.asarray(cfg.background, jnp.float32)

            def one(g, cam, k):  # pyright: ignore[reportRedeclaration] -- one per render mode, in exclusive branches
                out = splat.rasterize(
                    g.means,
                    g.quats,
                    g.scales,
                    g.opacities,
                    g.features.reshape(g.features.shape[0], -1, 3),
                    cam,
                    k,
                    height,
                    width,
                    cfg.splat,
                    render_mode="RGB+ED",
                    background=bg,
                    primitive=cfg.head.primitive,
                    surfel_depth=cfg.head.splat_surfel_depth,
                )
                return {"rgb": out.features, "depth": out.depth[..., None]}, out.stats.num_dropped

            images, dropped = per_target(one)(gaussians, c2w, intrinsics)
            return RenderOutput({o: images[o] for o in outputs}, jnp.sum(dropped, axis=1))

        r = cfg.decoder.canvas_ratio
        if height % cfg.decoder.token_stride or width % cfg.decoder.token_stride:
            raise ValueError(f"target size {height}x{width} must be a multiple of {cfg.decoder.token_stride}")
        hc, wc = height // r, width // r
        copies = jax.vmap(partition_opacities)(gaussians.opacities, self.partition(gaussians.features))

        def one(g, opac_s, cam, k):  # one scene, one target camera, all S copies
            out = splat.rasterize(g.means, g.quats, g.scales, opac_s, g.features, cam, k / r, hc, wc, cfg.splat)
            return out.features, out.stats.num_dropped

        canvas, dropped = jax.vmap(jax.vmap(one, (None, None, 0, 0)), (0, 0, 0, 0))(
            gaussians, copies, c2w, intrinsics
        )  # [B, T, S, hc, wc, F]
        b, t, s = canvas.shape[:3]
        canvas = append_target_rays(canvas, c2w, intrinsics, r)
        with jax.named_scope("decoder"):
            images = self.decoder(canvas.reshape(b * t, s, hc, wc, -1), outputs)
        images = {k: v.reshape(b, t, height, width, -1) for k, v in images.items()}
        return RenderOutput(images, jnp.sum(dropped, axis=1))

    def splat_opacities(self, gaussians: Gaussians):
        """The opacities :meth:`render` splats: ``[B, N]`` (colour) or the S copies ``[B, S, N]``."""
        if self.cfg.head.mode == "color":
            return gaussians.opacities
        return jax.vmap(partition_opacities)(gaussians.opacities, self.partition(gaussians.features))

    def __call__(
        self, images, c2w, intrinsics, target_c2w, target_intrinsics, outputs: tuple[str, ...] = ("rgb",)
    ) -> RenderOutput:
        g = self.reconstruct(images, c2w, intrinsics)
        return self.render(g, target_c2w, target_intrinsics, images.shape[2], images.shape[3], outputs)


def init_params(key: KeyArray, cfg: ModelConfig, num_views: int, height: int, width: int, num_targets: int = 1) -> dict:
    """Parameters for the model (every output head of ``cfg.outputs`` included).

    Runs one jitted forward pass on a dummy scene (Flax initialises lazily); wrap the call
    in ``jax.eval_shape`` to get shapes only.
    """
    images = jnp.full((1, num_views, height, width, 3), 0.5, jnp.float32)
    eye = jnp.broadcast_to(jnp.eye(4, dtype=jnp.float32), (1, num_views, 4, 4))
    intr = jnp.broadcast_to(jnp.array([width, width, width / 2, height / 2], jnp.float32), (1, num_views, 4))

    def init(k):
        return LongLRMPP(cfg).init(k, images, eye, intr, eye[:, :num_targets], intr[:, :num_targets], cfg.outputs)[
            "params"
        ]

    return jax.jit(init)(key)


def reconstruct(
    params: dict,
    cfg: ModelConfig,
    images: Float[ArrayLike, "B V H W 3"],
    c2w: Float[ArrayLike, "B V 4 4"],
    intrinsics: Float[ArrayLike, "B V 4"],
) -> Gaussians:
    """Images in [0, 1] + input cameras -> Gaussians (``N = V * h * w * K`` per scene)."""
    _check_views(images, c2w, intrinsics)
    return LongLRMPP(cfg).apply({"params": params}, images, c2w, intrinsics, method="reconstruct")  # pyright: ignore[reportReturnType] -- flax's apply is typed as maybe (out, variables); without mutable= it is out


def render(
    params: dict,
    cfg: ModelConfig,
    gaussians: Gaussians,
    c2w: Float[ArrayLike, "B T 4 4"],
    intrinsics: Float[ArrayLike, "B T 4"],
    height: int,
    width: int,
    outputs: tuple[str, ...] = ("rgb",),
) -> RenderOutput:
    """Render ``outputs`` ("rgb" and/or "depth") at T target cameras of size ``height x width``."""
    b = gaussians.means.shape[0]
    if c2w.ndim != 4 or c2w.shape[0] != b or c2w.shape[2:] != (4, 4):
        raise ValueError(f"target c2w must be [B={b}, T, 4, 4], got {c2w.shape}")
    if intrinsics.shape != (*c2w.shape[:2], 4):
        raise ValueError(f"target intrinsics must be {(*c2w.shape[:2], 4)}, got {intrinsics.shape}")
    return LongLRMPP(cfg).apply(  # pyright: ignore[reportReturnType] -- as above
        {"params": params}, gaussians, c2w, intrinsics, height, width, tuple(outputs), method="render"
    )


def fit_capacity(
    params: dict,
    cfg: ModelConfig,
    gaussians: Gaussians,
    c2w: Float[ArrayLike, "B T 4 4"],
    intrinsics: Float[ArrayLike, "B T 4"],
    height: int,
    width: int,
    *,
    headroom: float = 1.0,
    minimum: int = 0,
) -> ModelConfig:
    """``cfg`` with its splat capacity sized for :func:`render` of ``gaussians`` at these
    ``height x width`` cameras (:func:`llrmpp_jax.splat.fit_capacity` of the splats the render
    makes: the ``H/r x W/r`` canvases and all S partition copies in feature mode). Without it
    a render takes the trace-time buffer of ``intersections_per_gaussian`` slots per
    Gaussian, which a full-resolution colour render of a capture can overflow, dropping the
    farthest entries. A config that sets the capacity keeps it."""
    if cfg.splat.max_intersections is not None:
        return cfg
    r = cfg.decoder.canvas_ratio if cfg.head.mode == "feature" else 1
    opacities = LongLRMPP(cfg).apply({"params": params}, gaussians, method="splat_opacities")
    fitted = splat.fit_capacity(
        gaussians.means,
        gaussians.quats,
        gaussians.scales,
        opacities,  # pyright: ignore[reportArgumentType] -- as above
        c2w,
        jnp.asarray(intrinsics) / float(r),
        height // r,
        width // r,
        cfg.splat,
        headroom=headroom,
        minimum=minimum,
        primitive=cfg.head.primitive,
    )
    return dataclasses.replace(cfg, splat=fitted)


def partition_logits(params: dict, cfg: ModelConfig, gaussians: Gaussians) -> Float[Array, "... N S"]:
    """Feature mode: each Gaussian's S partition logits (``render`` splits its opacity by their
    softmax); the Gaussians may be batched ``[B, N]`` or one scene's ``[N]`` (a .gs file)."""
    if cfg.head.mode != "feature":
        raise ValueError(f"partition logits exist only in feature mode, the model is in {cfg.head.mode!r} mode")
    return LongLRMPP(cfg).apply({"params": params}, gaussians.features, method=lambda m, f: m.partition(f))  # pyright: ignore[reportReturnType] -- as above


def flatten_params(tree) -> dict[str, object]:
    """``{'a/b/c': leaf}``: parameter paths joined by ``/``."""
    return {
        "/".join(str(getattr(k, "key", k)) for k in path): leaf
        for path, leaf in jax.tree_util.tree_flatten_with_path(tree)[0]
    }


def expected_shapes(cfg: ModelConfig) -> dict:
    """``jax.eval_shape`` of the parameters of ``cfg`` (they do not depend on image size
    or view count, so the smallest valid input is used)."""
    m = cfg.size_multiple
    return jax.eval_shape(lambda k: init_params(k, cfg, 1, m, m), jax.random.key(0))


def check_params_fit(params, cfg: ModelConfig, source: str) -> None:
    """``ValueError`` naming the first parameter path whose presence or shape differs
    between ``params`` (arrays or shape structs) and the model of ``cfg``, with both shapes."""
    want, got = flatten_params(expected_shapes(cfg)), flatten_params(params)
    for path in sorted(set(want) | set(got)):
        w = tuple(want[path].shape) if path in want else None  # pyright: ignore[reportAttributeAccessIssue] -- the leaves of a params tree are arrays
        g = tuple(got[path].shape) if path in got else None  # pyright: ignore[reportAttributeAccessIssue] -- as above
        if w != g:
            w_txt = "absent" if w is None else str(w)
            g_txt = "absent" if g is None else str(g)
            raise UserError(
                f"{source}: parameters do not fit the model config: first mismatch {path!r}: "
                f"model {w_txt}, checkpoint {g_txt} (another architecture? pass the matching --config)"
            )
