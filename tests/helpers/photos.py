"""Photos and a video made from the first photos of ../shared's fox capture, for the tests of
poses from photos and of ``reconstruct --images/--video``."""

from __future__ import annotations

import os

import imageio_ffmpeg
import numpy as np

from llrmpp_jax.data.image_io import read_image, write_image
from llrmpp_jax.data.resample import resize_image
from tests.helpers.environment import shared_path

FOX = 10  # the first photos of the fox capture: they overlap enough to register


def fox_photos(folder, size: int = 480) -> list[str]:
    """The first FOX photos of the fox capture, shrunk to ``size`` px high, into ``folder``
    (created); their names."""
    src = shared_path("data", "fox", "images")
    os.makedirs(folder)
    names = sorted(os.listdir(src))[:FOX]
    for n in names:
        image = read_image(os.path.join(src, n))
        h, w = image.shape[:2]
        write_image(os.path.join(folder, n), resize_image(image, (size, round(w * size / h))))
    return names


def fox_video(path: str, size: int = 320, fps: int = 5) -> int:
    """An H.264 video of the FOX photos at ``size`` px high, ``fps`` frames a second; the
    number of frames."""
    folder = os.path.join(os.path.dirname(path), "video_frames")
    frames = [read_image(os.path.join(folder, n)) for n in fox_photos(folder, size)]
    h, w = frames[0].shape[:2]
    w -= w % 2  # yuv420p needs even sides
    writer = imageio_ffmpeg.write_frames(path, (w, h), fps=fps, quality=9, macro_block_size=1)
    writer.send(None)
    for f in frames:
        writer.send(np.ascontiguousarray((f[:, :w] * 255).round().astype(np.uint8)))
    writer.close()
    return len(frames)
