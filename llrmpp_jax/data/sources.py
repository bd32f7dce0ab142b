"""Where an experiment's scenes come from: :func:`scene_source` turns a
:class:`~llrmpp_jax.experiment.DataConfig` into the training scenes or the held-out ones.

Procedural data: training seeds from 0, held-out seeds from ``eval_seed_offset``
(:class:`OffsetSource`), so they never meet. Real data: the scenes under ``path`` (held out:
``eval_path`` in the split ``eval_split`` when set, only the scenes its ``scene_list`` names
when it has one). When the held-out evaluation reads the training scenes
(``DataConfig.eval_reads_training_scenes``), training loses the frames the evaluation
targets (:class:`WithoutEvalTargets`).
"""

from __future__ import annotations

import functools
import os
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from llrmpp_jax.data import formats
from llrmpp_jax.data.batching import FileSource, ProceduralSource, SceneSource
from llrmpp_jax.data.scene import Scene
from llrmpp_jax.data.selection import every_nth

if TYPE_CHECKING:  # experiment imports data (ProceduralConfig): no runtime import back
    from llrmpp_jax.experiment import DataConfig

EVAL_EVERY = 8  # real held-out scenes: targets every 8th frame (the paper's protocol, data.held_out.eval_split)


def scene_source(data: DataConfig, held_out: bool = False) -> SceneSource:
    """Training scenes, or with ``held_out`` those :func:`~llrmpp_jax.data.held_out.eval_samples`
    reads. Real training data that is also the held-out data
    (``DataConfig.eval_reads_training_scenes``) loses the evaluation's target frames
    (:class:`WithoutEvalTargets`)."""
    if data.kind == "procedural":
        return OffsetSource(ProceduralSource(data.procedural), data.eval_seed_offset if held_out else 0)
    if held_out and data.held_out_list is not None:
        paths = formats.listed_scenes(data.held_out_path, data.held_out_list)
    else:
        paths = formats.dataset_scenes(data.held_out_path if held_out else data.path, data.kind)
    files = FileSource(paths, functools.partial(formats.read_scene, kind=data.kind))
    if held_out or not data.eval_reads_training_scenes:
        return files
    evaluated = scene_source(data, held_out=True).paths[: data.num_eval_scenes]
    return WithoutEvalTargets(files, frozenset(os.path.abspath(p) for p in evaluated), data.eval_max_frames)


def held_out_description(data: DataConfig) -> str:
    """One line naming the held-out scenes: the split, the folder and the scene list (or
    the procedural seeds), and how many are evaluated at most."""
    if data.kind == "procedural":
        return f"{data.num_eval_scenes} procedural scenes from seed {data.eval_seed_offset}"
    split = f"split {data.eval_split}: " if data.eval_split else ""
    listed = f" named in {data.held_out_list}" if data.held_out_list else ""
    return f"{split}the first {data.num_eval_scenes} scenes{listed} in {data.held_out_path}"


@dataclass(frozen=True)
class WithoutEvalTargets:
    """Training scenes of a dataset the held-out evaluation also reads: the scenes at the
    absolute paths ``evaluated`` (those :func:`~llrmpp_jax.data.held_out.eval_samples` takes:
    the first ``num_eval_scenes`` of the folder or of its scene list) lose the frames the
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
