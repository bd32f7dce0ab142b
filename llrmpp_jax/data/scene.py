"""The ``Scene`` record every reader returns and every consumer reads.

A scene is a list of frames: OpenCV camera-to-world poses and pinhole pixel intrinsics
are held in memory (float64, exactly as read), images and depth maps are loaded lazily,
one frame at a time, through loader callables. Construction validates the cameras, so a
``Scene`` that exists has finite rigid poses and positive focal lengths; loading validates
each image and depth map against the frame's recorded size.

Frames from a real lens may carry distortion coefficients; :meth:`Scene.image` removes the
distortion, optionally after resizing to a smaller size first (the map is exact at any size
because the coefficients act on normalised coordinates, and undistorting the small image is
much cheaper than undistorting the full one).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np

from llrmpp_jax.array_typing import Float, Int, IntLike
from llrmpp_jax.data.distortion import undistort_image
from llrmpp_jax.data.resample import resize_depth, resize_image
from llrmpp_jax.errors import UserError
from llrmpp_jax.geometry import resize_intrinsics, validate_cameras

ImageLoader = Callable[[int], np.ndarray]  # frame index -> [H, W, 3] float32 in [0, 1]
DepthLoader = Callable[[int], np.ndarray]  # frame index -> [H, W] float32 metres, 0 = invalid


@dataclass(frozen=True, eq=False)
class Scene:
    """One multi-view capture.

    Attributes:
      name: scene identifier (dataset hash, folder name, procedural seed).
      c2w: ``[frames, 4, 4]`` float64 OpenCV camera-to-world.
      intrinsics: ``[frames, 4]`` float64 pinhole pixel ``(fx, fy, cx, cy)`` at the frame's size.
      hw: ``[frames, 2]`` int64 image size ``(H, W)`` of each frame as stored.
      frame_names: one string naming each frame (usually the image path), used in errors.
      image_fn: loader for frame i's image as stored, ``[H, W, 3]`` float32 in [0, 1].
      depth_fn: loader for frame i's metric z-depth ``[H, W]`` float32 (0 = invalid), or None.
      distortion: ``[frames, 5]`` OpenCV ``(k1, k2, p1, p2, k3)`` of the stored images, or None
        (pinhole). Images and depth returned by :meth:`image` / :meth:`depth` are undistorted.
    """

    name: str
    c2w: Float[np.ndarray, "frames 4 4"]
    intrinsics: Float[np.ndarray, "frames 4"]
    hw: Int[np.ndarray, "frames 2"]
    frame_names: tuple[str, ...]
    image_fn: ImageLoader
    depth_fn: DepthLoader | None = None
    distortion: Float[np.ndarray, "frames 5"] | None = None

    def __post_init__(self) -> None:
        c2w = np.asarray(self.c2w, dtype=np.float64)
        intrinsics = np.asarray(self.intrinsics, dtype=np.float64)
        hw = np.asarray(self.hw, dtype=np.int64)
        n = c2w.shape[0] if c2w.ndim == 3 else -1
        if n == 0:
            raise UserError(f"scene {self.name!r}: empty scene (no usable frames)")
        validate_cameras(c2w, intrinsics, name=f"scene {self.name!r}", frame_names=self.frame_names)
        if hw.shape != (n, 2) or (hw <= 0).any():
            raise UserError(f"scene {self.name!r}: hw must be positive [frames={n}, 2] (H, W), got {hw.shape}")
        if len(self.frame_names) != n:
            raise UserError(f"scene {self.name!r}: frame_names has {len(self.frame_names)} entries, expected {n}")
        if self.distortion is not None:
            distortion = np.asarray(self.distortion, dtype=np.float64)
            if distortion.shape != (n, 5) or not np.isfinite(distortion).all():
                raise UserError(
                    f"scene {self.name!r}: distortion must be finite [frames={n}, 5] (k1, k2, p1, p2, k3), "
                    f"got shape {distortion.shape}"
                )
            object.__setattr__(self, "distortion", distortion if distortion.any() else None)
        object.__setattr__(self, "c2w", c2w)
        object.__setattr__(self, "intrinsics", intrinsics)
        object.__setattr__(self, "hw", hw)
        object.__setattr__(self, "frame_names", tuple(self.frame_names))

    def __len__(self) -> int:
        return self.c2w.shape[0]

    @property
    def has_depth(self) -> bool:
        return self.depth_fn is not None

    def image(self, i: IntLike, hw: tuple[int, int] | None = None) -> Float[np.ndarray, "H W 3"]:
        """Frame i's pinhole image ``[H, W, 3]`` float32 in [0, 1], resized to ``hw`` if given
        (intrinsics then follow :func:`~llrmpp_jax.geometry.resize_intrinsics`).
        ``ValueError`` naming the frame if the stored image does not have the recorded size."""
        img = self.image_fn(int(i))
        h, w = (int(v) for v in self.hw[i])
        if img.shape != (h, w, 3):
            raise UserError(
                f"scene {self.name!r}, frame {i} ({self.frame_names[i]}): image has shape {img.shape}, "
                f"expected [{h}, {w}, 3] from the frame's recorded size"
            )
        if hw is not None:
            img = resize_image(img, hw)
        if self.distortion is not None:
            img = undistort_image(img, self._intrinsics_at(i, img.shape[:2]), self.distortion[i])
        return img

    def depth(self, i: IntLike, hw: tuple[int, int] | None = None) -> Float[np.ndarray, "H W"]:
        """Frame i's z-depth ``[H, W]`` float32 metres (0 = invalid), nearest-resized to ``hw``."""
        if self.depth_fn is None:
            raise UserError(f"scene {self.name!r} has no depth maps")
        depth = self.depth_fn(int(i))
        h, w = (int(v) for v in self.hw[i])
        if depth.shape != (h, w):
            raise UserError(
                f"scene {self.name!r}, frame {i} ({self.frame_names[i]}): depth map has shape {depth.shape}, "
                f"expected [{h}, {w}] (the size of its image)"
            )
        if hw is not None:
            depth = resize_depth(depth, hw)
        if self.distortion is not None:
            depth = undistort_image(depth, self._intrinsics_at(i, depth.shape), self.distortion[i], nearest=True)
        return depth

    def _intrinsics_at(self, i: IntLike, hw: tuple[int, int]) -> np.ndarray:
        return resize_intrinsics(self.intrinsics[i], tuple(self.hw[i]), hw)  # pyright: ignore[reportReturnType] -- NumPy in, NumPy out

    def subset(self, indices: Sequence[int] | Int[np.ndarray, " views"]) -> Scene:
        """The scene restricted to ``indices`` (in that order); loaders are re-indexed."""
        idx = np.asarray(indices, dtype=np.int64)
        if idx.ndim != 1 or idx.size == 0 or (idx < 0).any() or (idx >= len(self)).any():
            raise UserError(
                f"scene {self.name!r}: subset indices must be a non-empty list in [0, {len(self)}), got {indices}"
            )
        image_fn, depth_fn = self.image_fn, self.depth_fn
        return dataclasses.replace(
            self,
            c2w=self.c2w[idx],
            intrinsics=self.intrinsics[idx],
            hw=self.hw[idx],
            frame_names=tuple(self.frame_names[i] for i in idx),
            image_fn=lambda i: image_fn(int(idx[i])),
            depth_fn=None if depth_fn is None else (lambda i: depth_fn(int(idx[i]))),
            distortion=None if self.distortion is None else self.distortion[idx],
        )


def in_memory_scene(
    name: str,
    images: Float[np.ndarray, "frames H W 3"],
    c2w: Float[np.ndarray, "frames 4 4"],
    intrinsics: Float[np.ndarray, "frames 4"],
    depth: Float[np.ndarray, "frames H W"] | None = None,
) -> Scene:
    """A ``Scene`` over arrays already in memory (procedural scenes, tests)."""
    images = np.asarray(images, dtype=np.float32)
    if images.ndim != 4 or images.shape[-1] != 3:
        raise UserError(f"images: expected shape [frames, H, W, 3], got {images.shape}")
    n, h, w, _ = images.shape
    if depth is not None:
        depth = np.asarray(depth, dtype=np.float32)
        if depth.shape != (n, h, w):
            raise UserError(f"depth: expected shape [{n}, {h}, {w}] (same as images), got {depth.shape}")
    return Scene(
        name=name,
        c2w=c2w,
        intrinsics=intrinsics,
        hw=np.tile(np.array([[h, w]], dtype=np.int64), (n, 1)),
        frame_names=tuple(f"{name}/{i}" for i in range(n)),
        image_fn=lambda i: images[i],
        depth_fn=None if depth is None else (lambda i: depth[i]),
    )
