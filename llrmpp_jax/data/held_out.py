"""The held-out evaluation's samples: the paper's split of real scenes (:func:`eval_split`:
targets every :data:`~llrmpp_jax.data.sources.EVAL_EVERY` th frame, k-means or uniform
inputs) and, for procedural data, a fixed draw of the training view sampler per scene
(:func:`eval_samples`)."""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

from llrmpp_jax.data import formats
from llrmpp_jax.data.preprocess import make_sample
from llrmpp_jax.data.scene import Scene
from llrmpp_jax.data.selection import checked_inputs, eval_views, every_nth, training_views
from llrmpp_jax.data.sources import EVAL_EVERY, scene_source
from llrmpp_jax.data.stage_batches import needs_depth, view_geometry

if TYPE_CHECKING:  # experiment imports data (ProceduralConfig): no runtime import back
    from llrmpp_jax.experiment import DataConfig, ExperimentConfig, StageConfig


def eval_split(data: DataConfig, num_inputs: int, scene: Scene, path: str | None = None,
               index: dict[str, dict] | None = None, every: int = EVAL_EVERY) -> tuple[np.ndarray, np.ndarray, str]:
    """The paper's evaluation split of one real held-out scene: ``(inputs, targets, how)``,
    ``how`` a line saying what was used (see :class:`~llrmpp_jax.experiment.DataConfig`).
    k-means inputs come from, in this order: the scene's Long-LRM JSON at ``path``, the
    entry of ``scene.name`` in ``index`` (:func:`~llrmpp_jax.data.formats.read_kmeans_index`),
    else Long-LRM's k-means computed here."""
    n, limit = len(scene), data.eval_max_frames
    if data.eval_inputs == "uniform":
        inputs, targets = eval_views(scene.c2w, num_inputs, every, limit, inputs="uniform")
        first = limit is not None and n >= limit
        used = limit if first else n
        how = (f"targets every {every}th of {'the first' if first else 'all'} {used} frames, "
               f"{num_inputs} inputs spread uniformly over the other {used - len(targets)}")
        if limit is not None and n < limit:
            how = f"only {n} frames, fewer than {limit}: {how}"
        return inputs, targets, how
    key = f"fold_{every}_kmeans_{num_inputs}_input"
    if limit is None and data.kind == "long_lrm" and path is not None:
        cached = formats.cached_kmeans_inputs(path, every, num_inputs, n)
        if cached is not None:
            return cached, every_nth(n, every), f"inputs: the scene JSON's cached '{key}'"
    if limit is None and index is not None and key in index.get(scene.name, {}):
        inputs = checked_inputs(index[scene.name][key], n, num_inputs, f"{data.eval_index}: {scene.name} '{key}'")
        return inputs, every_nth(n, every), f"inputs: '{key}' of {data.eval_index}"
    inputs, targets = eval_views(scene.c2w, num_inputs, every, limit)
    return inputs, targets, "inputs: Long-LRM's k-means (scikit-learn KMeans, random_state=0, n_init='auto')"


def eval_samples(exp: ExperimentConfig, stage: StageConfig) -> tuple[list[dict], list[str]]:
    """Held-out samples, deterministic. Real data: the paper protocol (:func:`eval_split`,
    printing per scene what it used). Procedural: the training view sampler with a fixed
    seed per scene (procedural scenes are short paths, so every-8th targets would be too
    sparse)."""
    source = scene_source(exp.data, held_out=True)
    geom = view_geometry(stage, exp.model.size_multiple, train=False)
    with_depth = needs_depth(exp)
    index = formats.read_kmeans_index(exp.data.eval_index) if exp.data.eval_index else None
    samples, names = [], []
    for i in range(min(exp.data.num_eval_scenes, len(source))):
        scene = source.load(i)
        if exp.data.kind == "procedural":
            rng = np.random.default_rng([exp.seed, 7, i])
            inputs, targets = training_views(rng, len(scene), stage.num_inputs, stage.num_targets,
                                             exp.data.eval_span, exp.data.eval_span, input_weight=0.0)
        else:
            inputs, targets, how = eval_split(exp.data, stage.num_inputs, scene, source.paths[i], index)
        samples.append(make_sample(scene, inputs, targets, geom, rng=None, with_depth=with_depth))
        if exp.data.kind != "procedural":
            h, w = samples[-1]["input_images"].shape[-3:-1]
            print(f"eval scene {scene.name}: {len(inputs)} inputs, {len(targets)} targets, views {h}x{w} (HxW); {how}")
        names.append(scene.name)
    return samples, names
