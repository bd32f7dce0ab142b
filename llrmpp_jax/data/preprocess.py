"""From a scene and chosen frames to model-ready views, with exact intrinsics updates.

Per frame, in Long-LRM's order (reference facts §3.3):

1. **resize** keeping the aspect ratio to height ``resize_h`` (or width ``resize_w``),
   then round both sides to a multiple of ``multiple`` (the patch size): ``round(x / m) * m``;
2. **crop** an integer box: the centred square (``square_crop``), then optionally a random
   **zoom** box of ``r`` times the side (``r ~ U(zoom_min, 1)``, one ``r`` and position per
   sample, shared by all its views) that is resized back to the pre-zoom size.

Each step updates ``(fx, fy, cx, cy)`` exactly through :mod:`llrmpp_jax.geometry` (unlike
Long-LRM's zoom, which leaves ``cx, cy`` unchanged). Depth maps are not blended: each output
pixel takes the stored sample under its centre, found through the composed mapping. Then the Long-LRM scene normalisation
is applied to inputs and targets together, and depth is scaled with the scene.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from llrmpp_jax.array_typing import Float, Int
from llrmpp_jax.data.resample import remap, resize_image
from llrmpp_jax.data.scene import Scene
from llrmpp_jax.geometry import crop_intrinsics, normalize_scene, resize_intrinsics


@dataclass(frozen=True)
class ViewGeometry:
    """Output image geometry. ``resize_h`` / ``resize_w``: target height or width before
    rounding (at most one None = keep the aspect; both None = keep the stored size);
    ``multiple``: side multiple (patch size); ``square_crop``: centre-crop to a square;
    ``zoom_min``: smallest zoom-crop fraction (1.0 = no zoom augmentation);
    ``zoom_random_position``: place the zoom box at random (else centred, as Long-LRM)."""

    resize_h: int | None = None
    resize_w: int | None = None
    multiple: int = 8
    square_crop: bool = False
    zoom_min: float = 1.0
    zoom_random_position: bool = True

    def __post_init__(self) -> None:
        if self.multiple < 1 or not 0.0 < self.zoom_min <= 1.0:
            raise ValueError(f"ViewGeometry: need multiple >= 1 and 0 < zoom_min <= 1, got {self}")


def resized_size(hw: tuple[int, int], geom: ViewGeometry) -> tuple[int, int]:
    """Step 1's output size for a stored size ``hw`` (Long-LRM's rounding rule)."""
    h, w = int(hw[0]), int(hw[1])
    rh, rw = geom.resize_h, geom.resize_w
    if rh is None and rw is None:
        rh, rw = h, w
    elif rw is None:
        rw = int(rh / h * w)
    elif rh is None:
        rh = int(rw / w * h)
    m = geom.multiple
    out = (int(round(rh / m)) * m, int(round(rw / m)) * m)
    if min(out) <= 0:
        raise ValueError(f"resized size {out} from {hw} with {geom} is empty; choose a larger resize or smaller multiple")
    return out


def crop_box(
    hw: tuple[int, int], geom: ViewGeometry, rng: np.random.Generator | None
) -> tuple[int, int, int, int]:
    """Step 2's integer box ``(top, left, height, width)`` inside an image of size ``hw``.
    ``rng`` draws the zoom (None = no zoom, e.g. at evaluation)."""
    h, w = hw
    top, left = 0, 0
    if geom.square_crop:
        side = min(h, w)
        top, left, h, w = (h - side) // 2, (w - side) // 2, side, side
    if rng is not None and geom.zoom_min < 1.0:
        r = rng.uniform(geom.zoom_min, 1.0)
        ch, cw = max(1, int(round(r * h))), max(1, int(round(r * w)))
        if geom.zoom_random_position:
            dy, dx = int(rng.integers(0, h - ch + 1)), int(rng.integers(0, w - cw + 1))
        else:
            dy, dx = (h - ch) // 2, (w - cw) // 2
        top, left, h, w = top + dy, left + dx, ch, cw
    return top, left, h, w


def output_size(hw: tuple[int, int], geom: ViewGeometry) -> tuple[int, int]:
    """Final view size for stored size ``hw`` (after resize and square crop; the zoom keeps it)."""
    rh, rw = resized_size(hw, geom)
    return (min(rh, rw),) * 2 if geom.square_crop else (rh, rw)


def load_views(
    scene: Scene,
    indices: Int[np.ndarray, "K"],
    resized_hw: tuple[int, int],
    box: tuple[int, int, int, int],
    out_hw: tuple[int, int],
    with_depth: bool,
) -> tuple[Float[np.ndarray, "K H W 3"], Float[np.ndarray, "K 4"], Float[np.ndarray, "K H W"] | None]:
    """Load frames ``indices`` resized to ``resized_hw``, cropped to ``box`` and resized to
    ``out_hw``: ``(images, intrinsics, depth or None)``. Depth is not resampled twice: each
    output pixel takes the stored depth sample under its centre (nearest), found through
    the output and stored intrinsics (the same camera ray)."""
    top, left, ch, cw = box
    images, intr, depths = [], [], []
    for i in indices:
        img = scene.image(int(i), resized_hw)[top : top + ch, left : left + cw]
        images.append(resize_image(img, out_hw))
        k = resize_intrinsics(scene.intrinsics[i], tuple(scene.hw[i]), resized_hw)
        k = resize_intrinsics(crop_intrinsics(k, top, left), (ch, cw), out_hw)
        intr.append(k)
        if with_depth:
            k0 = scene.intrinsics[i]
            x = k0[2] + k0[0] * (np.arange(out_hw[1]) + 0.5 - k[2]) / k[0]
            y = k0[3] + k0[1] * (np.arange(out_hw[0]) + 0.5 - k[3]) / k[1]
            src = np.stack(np.meshgrid(x, y, indexing="xy"), axis=-1)
            depths.append(remap(scene.depth(int(i)), src, nearest=True))
    return (
        np.stack(images).astype(np.float32),
        np.stack(intr),
        np.stack(depths).astype(np.float32) if with_depth else None,
    )


def make_sample(
    scene: Scene,
    inputs: Int[np.ndarray, "V"],
    targets: Int[np.ndarray, "T"],
    geom: ViewGeometry,
    rng: np.random.Generator | None = None,
    with_depth: bool = False,
    scene_scale: float = 1.0,
) -> dict[str, np.ndarray]:
    """One model-ready sample (the batch layout of :mod:`llrmpp_jax.data.batching`,
    without the batch axis), normalised from the input cameras."""
    if with_depth and not scene.has_depth:
        raise ValueError(f"scene {scene.name!r}: depth requested but the scene has no depth maps")
    resized = resized_size(tuple(scene.hw[inputs[0]]), geom)
    out_hw = output_size(tuple(scene.hw[inputs[0]]), geom)
    box = crop_box(resized, geom, rng)
    in_img, in_k, _ = load_views(scene, inputs, resized, box, out_hw, False)
    tg_img, tg_k, tg_depth = load_views(scene, targets, resized, box, out_hw, with_depth)
    in_c2w, tg_c2w, _, scale = normalize_scene(scene.c2w[inputs], scene.c2w[targets], scene_scale=scene_scale)
    sample = {
        "input_images": in_img,
        "input_c2w": in_c2w.astype(np.float32),
        "input_intrinsics": in_k.astype(np.float32),
        "target_images": tg_img,
        "target_c2w": tg_c2w.astype(np.float32),
        "target_intrinsics": tg_k.astype(np.float32),
    }
    if with_depth:
        sample["target_depth"] = (tg_depth * np.float32(scale)).astype(np.float32)
    return sample
