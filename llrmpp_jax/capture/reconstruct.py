"""Reconstruct one capture: choose the views, report on the cameras, run the model once
(timed, compile apart) and package the Gaussians as a :class:`~.scene_file.SavedScene`.

View size: ``size=(H, None)`` resizes to height H keeping the capture's aspect ratio (the
width rounded to the model's size multiple, so a portrait capture stays portrait);
``size=(H, W)`` takes exactly that size (the intrinsics follow exactly, so a slight aspect
change is not a distortion of the geometry); ``square_crop`` centre-crops to a square.
"""

from __future__ import annotations

import functools
import os
import time
from dataclasses import dataclass

import jax
import numpy as np

from llrmpp_jax.array_typing import Float, Int
from llrmpp_jax.capture.scene_file import SavedScene
from llrmpp_jax.compile_cache import CompileWatch
from llrmpp_jax.config import ModelConfig
from llrmpp_jax.data.preprocess import ViewGeometry, crop_box, load_views, output_size, resized_size
from llrmpp_jax.data.scene import Scene
from llrmpp_jax.data.selection import every_nth, kmeans_inputs
from llrmpp_jax.errors import UserError
from llrmpp_jax.gaussians import Gaussians
from llrmpp_jax.geometry import crop_intrinsics, normalize_scene, resize_intrinsics
from llrmpp_jax.model import reconstruct


def select_views(
    scene: Scene, num_inputs: int, inputs: list[int] | None = None, every: int = 8
) -> tuple[Int[np.ndarray, " V"], Int[np.ndarray, " T"]]:
    """``(inputs, targets)`` frame indices. Targets: every ``every``-th frame (the paper's
    held-out split) not among the inputs. Inputs: ``inputs`` as given (checked against the
    frame count), else ``num_inputs`` frames by k-means over the non-target frames."""
    n = len(scene)
    if inputs is not None:
        idx = np.asarray(inputs, np.int64)
        bad = idx[(idx < 0) | (idx >= n)]
        if bad.size:
            raise UserError(
                f"--inputs: index {int(bad[0])} is out of range; scene {scene.name!r} has {n} frames (0..{n - 1})"
            )
        if len(set(idx.tolist())) != idx.size:
            raise UserError(f"--inputs: indices must be distinct, got {idx.tolist()}")
        return np.sort(idx), np.setdiff1d(every_nth(n, every), idx)
    if num_inputs < 1:
        raise UserError(f"--num-inputs must be >= 1, got {num_inputs}")
    targets = every_nth(n, every)
    rest = np.setdiff1d(np.arange(n), targets)
    if len(rest) < num_inputs:
        raise UserError(
            f"scene {scene.name!r}: {n} usable frames leave {len(rest)} non-target frames, "
            f"fewer than the {num_inputs} inputs requested (--num-inputs)"
        )
    return kmeans_inputs(scene.c2w, rest, num_inputs), targets


def view_size(
    scene: Scene, frame: int, size: tuple[int, int | None], multiple: int, square_crop: bool = False
) -> tuple[ViewGeometry, tuple[int, int], tuple[int, int, int, int], tuple[int, int]]:
    """``(geometry, resized_hw, crop_box, out_hw)`` for views of ``scene`` (sized from
    ``frame``). ``ValueError`` if a side given in ``size`` is not a multiple of ``multiple``."""
    h, w = size
    for name, side in (("height", h), ("width", w)):
        if side is not None and (side <= 0 or side % multiple):
            raise UserError(
                f"--size: {name} {side} is not a positive multiple of the model's patch multiple {multiple}"
            )
    geom = ViewGeometry(resize_h=h, resize_w=w, multiple=multiple, square_crop=square_crop)
    hw = tuple(int(v) for v in scene.hw[frame])
    resized = resized_size(hw, geom)  # pyright: ignore[reportArgumentType] -- an image's two sides
    return geom, resized, crop_box(resized, geom), output_size(hw, geom)  # pyright: ignore[reportArgumentType] -- as above


@dataclass(frozen=True)
class CameraReport:
    """What the camera sanity check found (``lines()`` prints it)."""

    scene: str
    num_frames: int
    missing: tuple[str, ...]  # reader warnings about frames dropped (missing files)
    image_sizes: dict[str, int]  # "WxH" -> frame count
    distortion: str
    intrinsics_spread: dict[str, tuple[float, float]]  # fx, fy, cx, cy -> (min, max)
    extent: float  # largest side of the input cameras' bounding box, capture units
    scale: float  # normalisation s: scene units per capture unit
    view_hw: tuple[int, int]
    inputs: tuple[str, ...]
    targets: tuple[str, ...]

    def lines(self) -> list[str]:
        sizes = ", ".join(f"{k} x{v}" for k, v in self.image_sizes.items())
        spread = ", ".join(f"{k} {lo:.1f}..{hi:.1f}" for k, (lo, hi) in self.intrinsics_spread.items())
        return [
            f"scene {self.scene}: {self.num_frames} frames usable"
            + (f"; dropped: {'; '.join(self.missing)}" if self.missing else "; none missing"),
            f"  image sizes (WxH): {sizes}; lens: {self.distortion}",
            f"  intrinsics at stored size: {spread}",
            "  poses: all finite rotations (checked on read)",
            f"  input cameras span {self.extent:.4g} capture units; normalisation scale {self.scale:.4g} "
            f"(scene units per capture unit); views {self.view_hw[0]}x{self.view_hw[1]} (HxW)",
            f"  inputs ({len(self.inputs)}): {', '.join(self.inputs)}",
            f"  held-out targets ({len(self.targets)}): {', '.join(self.targets) or 'none'}",
        ]


def _short(name: str) -> str:
    return os.path.basename(name)


def camera_report(
    scene: Scene,
    inputs: np.ndarray,
    targets: np.ndarray,
    view_hw: tuple[int, int],
    missing: tuple[str, ...] = (),
    normalize: bool = True,
) -> CameraReport:
    """The camera sanity report of ``scene`` with the chosen views (host-side, no compile);
    ``normalize=False``: the capture's frame is kept (scale 1)."""
    sizes: dict[str, int] = {}
    for h, w in scene.hw.tolist():
        sizes[f"{w}x{h}"] = sizes.get(f"{w}x{h}", 0) + 1
    if scene.distortion is None:
        lens = "pinhole (no distortion)"
    else:
        d = scene.distortion
        lens = (
            f"OpenCV distortion removed on load (k1 {d[:, 0].min():.4g}..{d[:, 0].max():.4g}, "
            f"k2 {d[:, 1].min():.4g}..{d[:, 1].max():.4g})"
        )
    k = scene.intrinsics
    spread = {name: (float(k[:, i].min()), float(k[:, i].max())) for i, name in enumerate(("fx", "fy", "cx", "cy"))}
    pos = scene.c2w[inputs, :3, 3]
    scale = normalize_scene(scene.c2w[inputs])[-1] if normalize else 1.0
    return CameraReport(
        scene=scene.name,
        num_frames=len(scene),
        missing=tuple(missing),
        image_sizes=sizes,
        distortion=lens,
        intrinsics_spread=spread,
        extent=float((pos.max(0) - pos.min(0)).max()),
        scale=float(scale),
        view_hw=tuple(view_hw),  # pyright: ignore[reportArgumentType] -- an image's two sides
        inputs=tuple(_short(scene.frame_names[i]) for i in inputs),
        targets=tuple(_short(scene.frame_names[i]) for i in targets),
    )


@dataclass(frozen=True)
class Reconstruction:
    """:func:`reconstruct_scene`'s result: the saved scene, the input and target views as
    fed to the model (``[V|T, H, W, 3]``), and the timings (seconds)."""

    saved: SavedScene
    input_images: Float[np.ndarray, "V H W 3"]
    target_images: Float[np.ndarray, "T H W 3"]
    compile_s: float
    run_s: float  # median of the synced runs
    runs_s: tuple[float, ...]
    compile_note: str = ""  # the compile's seconds and whether it came from the compile cache


@functools.partial(jax.jit, static_argnames=("cfg",))
def _reconstruct(params, cfg, images, c2w, intrinsics) -> Gaussians:
    return reconstruct(params, cfg, images, c2w, intrinsics)


def reconstruct_scene(
    params: dict,
    cfg: ModelConfig,
    scene: Scene,
    inputs: Int[np.ndarray, " V"],
    targets: Int[np.ndarray, " T"],
    size: tuple[int, int | None],
    *,
    square_crop: bool = False,
    normalize: bool = True,
    repeats: int = 3,
    scene_path: str = "",
    scene_format: str = "",
) -> Reconstruction:
    """Run the model on the ``inputs`` of ``scene`` at ``size`` (see the module doc).

    Cameras are normalised from the inputs (Long-LRM §3.4; ``normalize=False`` keeps the
    capture's frame). Timing: the jitted reconstruction is compiled once (``compile_s``),
    then run ``repeats`` times with the device synced; ``run_s`` is the median.
    """
    if repeats < 1:
        raise UserError(f"repeats must be >= 1, got {repeats}")
    _, resized, box, out_hw = view_size(scene, int(inputs[0]), size, cfg.size_multiple, square_crop)
    in_img, in_k, _ = load_views(scene, inputs, resized, box, None, False)
    tg_img = (
        load_views(scene, targets, resized, box, None, False)[0]
        if len(targets)
        else np.zeros((0, *out_hw, 3), np.float32)
    )
    if normalize:
        _, all_c2w, transform, _ = normalize_scene(scene.c2w[inputs], scene.c2w)
    else:
        all_c2w, transform = scene.c2w.copy(), np.eye(4)
    all_k = np.stack(
        [
            resize_intrinsics(
                crop_intrinsics(resize_intrinsics(scene.intrinsics[i], tuple(scene.hw[i]), resized), box[0], box[1]),
                box[2:],
                out_hw,
            )
            for i in range(len(scene))
        ]
    )
    args = (
        jax.numpy.asarray(in_img[None]),
        jax.numpy.asarray(all_c2w[inputs][None], np.float32),
        jax.numpy.asarray(in_k[None], np.float32),
    )
    t0 = time.perf_counter()
    with CompileWatch() as watch:
        compiled = _reconstruct.lower(params, cfg, *args).compile()
    compile_s = time.perf_counter() - t0
    runs = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        g = jax.block_until_ready(compiled(params, *args))
        runs.append(time.perf_counter() - t0)
    saved = SavedScene(
        gaussians=Gaussians(*(np.asarray(x[0]) for x in g)),  # pyright: ignore[reportArgumentType] -- a NumPy array where jax.Array is annotated: both work
        model=cfg,
        c2w=all_c2w,  # pyright: ignore[reportArgumentType] -- NumPy arrays
        intrinsics=all_k,
        world_from_scene=np.linalg.inv(transform),
        frame_names=scene.frame_names,
        inputs=np.asarray(inputs, np.int64),
        targets=np.asarray(targets, np.int64),
        image_hw=tuple(out_hw),  # pyright: ignore[reportArgumentType] -- an image's two sides
        resized_hw=tuple(resized),  # pyright: ignore[reportArgumentType] -- as above
        crop_box=tuple(box),  # pyright: ignore[reportArgumentType] -- the crop box's four numbers
        scene_path=scene_path,
        scene_format=scene_format,
    )
    return Reconstruction(
        saved, in_img, tg_img, compile_s, float(np.median(runs)), tuple(runs), watch.describe(compile_s)
    )
