"""From a scene and chosen frames to model-ready views, with exact intrinsics updates.

Per frame, in Long-LRM's order (reference facts §3.3):

1. **resize** keeping the aspect ratio to height ``resize_h`` (or width ``resize_w``),
   then round both sides to a multiple of ``multiple`` (the patch size): ``round(x / m) * m``;
2. **square crop** (``square_crop``): the centred ``min(H, W)`` square;
3. **zoom** (Long-LRM's ``random_crop``, training only): ``r ~ U(zoom_min, 1)``, one ``r``
   per sample shared by its inputs and targets; the image is upsampled by ``1/r``
   (bilinear, ``align_corners=False``, to ``floor(H/r) x floor(W/r)`` as torch sizes it)
   and centre-cropped back to ``H x W`` at offset ``((floor(H/r) - H) // 2, (floor(W/r) -
   W) // 2)`` -- Long-LRM's exact sampling grid.

Each step updates ``(fx, fy, cx, cy)`` exactly through :mod:`llrmpp_jax.geometry`. For the
zoom that is ``f / r`` and ``c / r - offset``. Long-LRM itself writes ``f * floor(W/r) / W``
and leaves ``c`` unchanged, which is exact only when ``W/r`` is an integer, the offset is
exactly ``(W/r - W) / 2`` and the principal point is the image centre; otherwise its rays
are off by up to ``|c - W/2| (1/r - 1)`` px (an off-centre principal point), up to 1 px at
the centre (the two floors) and up to 0.5 px at the border (the focal rounding).

Depth maps are not blended: each output pixel takes the stored sample under its centre,
found through the composed mapping. Then the Long-LRM scene normalisation is applied to
inputs and targets together, and depth is scaled with the scene.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from llrmpp_jax.array_typing import Float, Int, IntLike
from llrmpp_jax.data.resample import remap
from llrmpp_jax.data.scene import Scene
from llrmpp_jax.errors import UserError
from llrmpp_jax.geometry import crop_intrinsics, normalize_scene, resize_intrinsics


@dataclass(frozen=True)
class ViewGeometry:
    """Output image geometry. ``resize_h`` / ``resize_w``: target height or width before
    rounding (at most one None = keep the aspect; both None = keep the stored size);
    ``multiple``: side multiple (patch size); ``square_crop``: centre-crop to a square;
    ``zoom_min``: smallest zoom fraction ``r`` (1.0 = no zoom augmentation; Long-LRM 0.77)."""

    resize_h: int | None = None
    resize_w: int | None = None
    multiple: int = 8
    square_crop: bool = False
    zoom_min: float = 1.0

    def __post_init__(self) -> None:
        if self.multiple < 1 or not 0.0 < self.zoom_min <= 1.0:
            raise UserError(f"ViewGeometry: need multiple >= 1 and 0 < zoom_min <= 1, got {self}")


def resized_size(hw: tuple[IntLike, IntLike], geom: ViewGeometry) -> tuple[int, int]:
    """Step 1's output size for a stored size ``hw`` (Long-LRM's rounding rule)."""
    h, w = int(hw[0]), int(hw[1])
    rh, rw = geom.resize_h, geom.resize_w
    if rh is None and rw is None:
        rh, rw = h, w
    elif rw is None:
        rw = int(rh / h * w)  # pyright: ignore[reportOptionalOperand] -- rh is set in this branch
    elif rh is None:
        rh = int(rw / w * h)
    m = geom.multiple
    out = (int(round(rh / m)) * m, int(round(rw / m)) * m)  # pyright: ignore[reportOptionalOperand] -- both are set by now
    if min(out) <= 0:
        raise UserError(
            f"resized size {out} from {hw} with {geom} is empty; choose a larger resize or smaller multiple"
        )
    return out


def crop_box(hw: tuple[int, int], geom: ViewGeometry) -> tuple[int, int, int, int]:
    """Step 2's integer box ``(top, left, height, width)`` inside an image of size ``hw``."""
    h, w = hw
    if not geom.square_crop:
        return 0, 0, h, w
    side = min(h, w)
    return (h - side) // 2, (w - side) // 2, side, side


def output_size(hw: tuple[IntLike, IntLike], geom: ViewGeometry) -> tuple[int, int]:
    """Final view size for stored size ``hw`` (after resize and square crop; the zoom keeps it)."""
    rh, rw = resized_size(hw, geom)
    return (min(rh, rw),) * 2 if geom.square_crop else (rh, rw)  # pyright: ignore[reportReturnType] -- two ints


def draw_zoom(geom: ViewGeometry, rng: np.random.Generator | None) -> float | None:
    """Step 3's ``r ~ U(zoom_min, 1)`` drawn from ``rng``; None (no zoom) without ``rng``
    (evaluation) or with ``zoom_min == 1`` (then nothing is drawn)."""
    if rng is None or geom.zoom_min >= 1.0:
        return None
    return float(rng.uniform(geom.zoom_min, 1.0))


def zoom_offset(hw: tuple[int, int], r: float) -> tuple[int, int]:
    """``(top, left)`` of Long-LRM's centre crop in the image upsampled by ``1/r``, whose
    size torch makes ``floor(side * (1/r))``."""
    scale = 1.0 / r
    return tuple((int(math.floor(float(n) * scale)) - n) // 2 for n in hw)  # pyright: ignore[reportReturnType] -- two ints, from the two of hw


def zoom_intrinsics(
    intrinsics: Float[np.ndarray, "... 4"], r: float, offset: tuple[int, int]
) -> Float[np.ndarray, "... 4"]:
    """Exact intrinsics after step 3: every coordinate scales by ``1/r``, then the crop
    moves the principal point by ``-(left, top)``."""
    return crop_intrinsics(np.asarray(intrinsics, np.float64) / r, offset[0], offset[1])  # pyright: ignore[reportReturnType] -- NumPy in, NumPy out


def zoom_image(image: Float[np.ndarray, "H W C"], r: float, offset: tuple[int, int]) -> Float[np.ndarray, "H W C"]:
    """Step 3 on one image: output pixel centre ``(j + 0.5, i + 0.5)`` samples the input
    bilinearly at ``((j + 0.5 + left) r, (i + 0.5 + top) r)``, as torch's ``interpolate``
    with ``scale_factor=1/r`` followed by the crop does (borders clamp)."""
    h, w = image.shape[:2]
    top, left = offset
    x = (np.arange(w) + 0.5 + left) * r
    y = (np.arange(h) + 0.5 + top) * r
    return remap(image, np.stack(np.meshgrid(x, y, indexing="xy"), axis=-1)).astype(np.float32)


def load_views(
    scene: Scene,
    indices: Int[np.ndarray, " views"],
    resized_hw: tuple[int, int],
    box: tuple[int, int, int, int],
    zoom: float | None,
    with_depth: bool,
) -> tuple[Float[np.ndarray, "views H W 3"], Float[np.ndarray, "views 4"], Float[np.ndarray, "views H W"] | None]:
    """Load frames ``indices`` resized to ``resized_hw``, cropped to ``box`` and zoomed by
    ``1/zoom`` (None = no zoom): ``(images, intrinsics, depth or None)``. Depth is not
    resampled twice: each output pixel takes the stored depth sample under its centre
    (nearest), found through the output and stored intrinsics (the same camera ray)."""
    top, left, ch, cw = box
    offset = None if zoom is None else zoom_offset((ch, cw), zoom)
    images, intr, depths = [], [], []
    for i in indices:
        img = scene.image(int(i), resized_hw)[top : top + ch, left : left + cw]
        k = crop_intrinsics(resize_intrinsics(scene.intrinsics[i], tuple(scene.hw[i]), resized_hw), top, left)
        if zoom is not None:
            img, k = zoom_image(img, zoom, offset), zoom_intrinsics(k, zoom, offset)  # pyright: ignore[reportArgumentType] -- offset is set whenever zoom is
        images.append(img)
        intr.append(k)
        if with_depth:
            k0 = scene.intrinsics[i]
            x = k0[2] + k0[0] * (np.arange(cw) + 0.5 - k[2]) / k[0]
            y = k0[3] + k0[1] * (np.arange(ch) + 0.5 - k[3]) / k[1]
            src = np.stack(np.meshgrid(x, y, indexing="xy"), axis=-1)
            depths.append(remap(scene.depth(int(i)), src, nearest=True))
    return (
        np.stack(images).astype(np.float32),
        np.stack(intr),
        np.stack(depths).astype(np.float32) if with_depth else None,
    )


def make_sample(
    scene: Scene,
    inputs: Int[np.ndarray, " V"],
    targets: Int[np.ndarray, " T"],
    geom: ViewGeometry,
    rng: np.random.Generator | None = None,
    with_depth: bool = False,
    scene_scale: float = 1.0,
    rescale: bool = True,
) -> dict[str, np.ndarray]:
    """One model-ready sample (the batch layout of :mod:`llrmpp_jax.data.batching`,
    without the batch axis), normalised from the input cameras
    (:func:`~llrmpp_jax.geometry.normalize_scene` with ``scene_scale`` and ``rescale``)."""
    if with_depth and not scene.has_depth:
        raise UserError(f"scene {scene.name!r}: depth requested but the scene has no depth maps")
    resized = resized_size(tuple(scene.hw[inputs[0]]), geom)
    box = crop_box(resized, geom)
    zoom = draw_zoom(geom, rng)
    in_img, in_k, _ = load_views(scene, inputs, resized, box, zoom, False)
    tg_img, tg_k, tg_depth = load_views(scene, targets, resized, box, zoom, with_depth)
    in_c2w, tg_c2w, _, scale = normalize_scene(
        scene.c2w[inputs], scene.c2w[targets], scene_scale=scene_scale, rescale=rescale
    )
    sample = {
        "input_images": in_img,
        "input_c2w": in_c2w.astype(np.float32),
        "input_intrinsics": in_k.astype(np.float32),
        "target_images": tg_img,
        "target_c2w": tg_c2w.astype(np.float32),
        "target_intrinsics": tg_k.astype(np.float32),
    }
    if with_depth:
        sample["target_depth"] = (tg_depth * np.float32(scale)).astype(np.float32)  # pyright: ignore[reportOptionalOperand] -- with_depth loads the depth
    sample["scene_scale"] = np.float32(scale)
    return sample
