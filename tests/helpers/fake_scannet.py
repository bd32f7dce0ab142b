"""A fake ScanNet export laid out by split (procedural rooms) and the scannet recipe's data
layout over it: for the tests of ``data/sources.py`` and of ``llrmpp eval --split``."""

import os

import numpy as np

from llrmpp_jax.data.formats import write_scannet_scene
from llrmpp_jax.data.scene import in_memory_scene
from llrmpp_jax.data.synthetic import ProceduralConfig, procedural_scene
from llrmpp_jax.experiment import DataConfig

ROOMS = {
    "train": ["scene0000_00", "scene0001_00"],
    "val": ["scene0011_00"],
    "test": ["scene0707_00", "scene0708_00", "scene0709_00"],
}
FRAMES = 9  # the evaluation targets every 8th: frames 0 and 8


def fake_scannet(root, size: int = 16, lists: dict[str, list[str]] | None = None) -> str:
    """ScanNet exported by split under ``root``: ``<split>/<room>/{color,depth,pose,intrinsic}``
    for the :data:`ROOMS` (procedural rooms, ``size`` pixels square, :data:`FRAMES` frames, depth
    on the millimetre grid), and ``scannetv2_<split>.txt`` naming ``lists[split]`` (default: the
    test list leaves ``scene0709_00`` out and puts ``scene0708_00`` first)."""
    lists = lists or {"train": ROOMS["train"], "val": ROOMS["val"], "test": ["scene0708_00", "scene0707_00"]}
    for seed, (split, rooms) in enumerate(ROOMS.items()):
        for i, room in enumerate(rooms):
            s = procedural_scene(10 * seed + i, ProceduralConfig(height=size, width=size, num_frames=FRAMES))
            images = np.stack([s.image(f) for f in range(FRAMES)])
            depth = np.stack([np.rint(s.depth(f) * 1000) / 1000 for f in range(FRAMES)])
            write_scannet_scene(
                in_memory_scene(room, images, s.c2w, s.intrinsics, depth),
                os.path.join(root, split, room),
                image_ext=".png",
                bits=8,
            )
    for split, names in lists.items():
        with open(os.path.join(root, f"scannetv2_{split}.txt"), "w") as f:
            f.write("".join(f"{n}\n" for n in names))
    return str(root)


def split_data(root: str, split: str = "test", **changes) -> DataConfig:
    """The scannet recipe's data layout under ``root``, evaluating ``split``."""
    return DataConfig(
        **{
            **dict(
                kind="scannet",
                path=os.path.join(root, "train"),
                eval_path=os.path.join(root, "{split}"),
                eval_split=split,
                scene_list=os.path.join(root, "scannetv2_{split}.txt"),
                num_eval_scenes=100,
            ),
            **changes,
        }
    )
