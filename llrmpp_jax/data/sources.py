"""Scene sources the held-out evaluation and training share: :func:`dataset_source` (the
scenes of a dataset folder or of a scene list), :class:`OffsetSource` (procedural scenes
from a seed on, so held-out seeds never meet training ones) and :class:`WithoutEvalTargets`
(training scenes that lose the frames the evaluation targets). An experiment's choice among
them is ``llrmpp_jax.experiment_data.scene_source``.
"""

from __future__ import annotations

import functools
import os
from dataclasses import dataclass

import numpy as np

from llrmpp_jax.data import formats
from llrmpp_jax.data.batching import FileSource, ProceduralSource
from llrmpp_jax.data.scene import Scene
from llrmpp_jax.data.selection import every_nth

EVAL_EVERY = 8  # real held-out scenes: targets every 8th frame (the paper's protocol, data.held_out.eval_split)


def dataset_source(path: str, kind: formats.Format, scene_list: str | None = None) -> FileSource:
    """The scenes of the dataset at ``path`` of format ``kind`` (a readable format of
    :func:`~llrmpp_jax.data.formats.read_scene`): every scene, or with ``scene_list`` (a text
    file of scene names, one a line) those it names, in its order."""
    paths = formats.listed_scenes(path, scene_list) if scene_list is not None else formats.dataset_scenes(path, kind)
    return FileSource(paths, functools.partial(formats.read_scene, kind=kind))


@dataclass(frozen=True)
class WithoutEvalTargets:
    """Training scenes of a dataset the held-out evaluation also reads: the scenes at the
    absolute paths ``evaluated`` (those the held-out evaluation takes, e.g. the first
    ``num_eval_scenes`` of the folder or of its scene list) lose the frames the
    evaluation targets, every :data:`EVAL_EVERY` th of the first ``max_frames``
    (:func:`~llrmpp_jax.data.held_out.eval_split`), so their scores are on views never
    trained on. The scenes' other frames, the evaluation's inputs among them, are trained on."""

    base: FileSource
    evaluated: frozenset[str]
    max_frames: int | None

    def __len__(self) -> int:
        return len(self.base)

    def load(self, index: int) -> Scene:
        scene = self.base.load(index)
        if os.path.abspath(self.base.paths[index]) not in self.evaluated:
            return scene
        n = len(scene) if self.max_frames is None else min(self.max_frames, len(scene))
        return scene.subset(np.setdiff1d(np.arange(len(scene)), every_nth(n, EVAL_EVERY)))


@dataclass(frozen=True)
class OffsetSource:
    """Procedural scenes from seed ``offset`` on (held-out seeds never meet training ones)."""

    base: ProceduralSource
    offset: int

    def __len__(self) -> int:
        return len(self.base) - self.offset

    def load(self, index: int) -> Scene:
        return self.base.load(self.offset + index)
