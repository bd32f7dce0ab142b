"""From an experiment to its data: the scenes (:func:`scene_source`), the training batches
of a stage (:func:`batch_config`) and the held-out samples (:func:`eval_samples`, the one
held-out set ``llrmpp train``, ``llrmpp eval`` and the ablation tables score on).

:mod:`llrmpp_jax.data` knows scenes, sources and :class:`~llrmpp_jax.data.BatchConfig`,
nothing of experiments; the choices an :class:`~llrmpp_jax.experiment.ExperimentConfig`
makes about them are read here.
"""

from __future__ import annotations

import os

import numpy as np

from llrmpp_jax.data import BatchConfig, ProceduralSource, ViewGeometry, formats, make_sample, training_views
from llrmpp_jax.data.batching import SceneSource
from llrmpp_jax.data.held_out import eval_split
from llrmpp_jax.data.scene import Scene
from llrmpp_jax.data.sources import EVAL_EVERY, OffsetSource, WithoutEvalTargets, dataset_source
from llrmpp_jax.experiment import DataConfig, ExperimentConfig, StageConfig


def scene_source(data: DataConfig, held_out: bool = False) -> SceneSource:
    """Training scenes, or with ``held_out`` those :func:`eval_samples` reads. Procedural:
    seeds from 0, held out from ``data.eval_seed_offset``. Real: the scenes under
    ``data.path`` (held out: ``data.held_out_path``, only those ``data.held_out_list``
    names when it has one); real training data that is also the held-out data
    (``DataConfig.eval_reads_training_scenes``) loses the evaluation's target frames
    (:class:`~llrmpp_jax.data.sources.WithoutEvalTargets`)."""
    if data.kind == "procedural":
        return OffsetSource(ProceduralSource(data.procedural), data.eval_seed_offset if held_out else 0)
    if held_out:
        return dataset_source(data.held_out_path, data.kind, data.held_out_list)  # pyright: ignore[reportArgumentType] -- a file dataset has a path (DataConfig checks it)
    files = dataset_source(data.path, data.kind)  # pyright: ignore[reportArgumentType] -- as above
    if not data.eval_reads_training_scenes:
        return files
    evaluated = scene_source(data, held_out=True).paths[: data.num_eval_scenes]  # pyright: ignore[reportAttributeAccessIssue] -- the source made here is a FileSource (a HeldOutSource for .base), which has it
    return WithoutEvalTargets(files, frozenset(os.path.abspath(p) for p in evaluated), data.eval_max_frames)


def held_out_description(data: DataConfig) -> str:
    """One line naming the held-out scenes: the split, the folder and the scene list (or
    the procedural seeds), and how many are evaluated at most."""
    if data.kind == "procedural":
        return f"{data.num_eval_scenes} procedural scenes from seed {data.eval_seed_offset}"
    split = f"split {data.eval_split}: " if data.eval_split else ""
    listed = f" named in {data.held_out_list}" if data.held_out_list else ""
    return f"{split}the first {data.num_eval_scenes} scenes{listed} in {data.held_out_path}"


def view_geometry(stage: StageConfig, multiple: int, train: bool = True) -> ViewGeometry:
    """``stage``'s image geometry, sides rounded to ``multiple``; ``train`` False (held-out
    views): no random zoom."""
    return ViewGeometry(
        resize_h=stage.resize_h,
        resize_w=stage.resize_w,
        multiple=multiple,
        square_crop=stage.square_crop,
        zoom_min=stage.zoom_min if train else 1.0,
    )


def needs_depth(exp: ExperimentConfig) -> bool:
    """Whether batches carry ground-truth target depth (a depth output or the Gaussian depth term)."""
    return "depth" in exp.model.outputs or exp.gaussian_depth_weight > 0


def batch_config(exp: ExperimentConfig, stage: StageConfig) -> BatchConfig:
    """The training batches of ``stage`` of ``exp``."""
    return BatchConfig(
        global_batch=stage.global_batch,
        num_inputs=stage.num_inputs,
        num_targets=stage.num_targets,
        geometry=view_geometry(stage, exp.model.size_multiple),
        min_span=stage.min_span,
        max_span=stage.max_span,
        input_weight=stage.input_weight,
        reverse_prob=stage.reverse_prob,
        shuffle_prob=stage.shuffle_prob,
        with_depth=needs_depth(exp),
        rescale=exp.data.rescale,
    )


def held_out_split(
    data: DataConfig,
    num_inputs: int,
    scene: Scene,
    path: str | None = None,
    index: dict[str, dict] | None = None,
    every: int = EVAL_EVERY,
) -> tuple[np.ndarray, np.ndarray, str]:
    """:func:`~llrmpp_jax.data.held_out.eval_split` of one held-out ``scene`` (read from
    ``path``) as ``data`` asks: its ``eval_inputs`` and ``eval_max_frames``, the k-means
    inputs cached in a Long-LRM scene's JSON or in ``index`` (read from ``data.eval_index``)."""
    return eval_split(
        scene,
        num_inputs,
        data.eval_inputs,
        data.eval_max_frames,
        json_path=path if data.kind == "long_lrm" else None,
        index=index,
        index_name=data.eval_index or "the index",
        every=every,
    )


def _procedural_views(exp: ExperimentConfig, stage: StageConfig, i: int, scene: Scene) -> tuple[np.ndarray, np.ndarray]:
    """Held-out views of procedural scene ``i``: the paper's split (``procedural_eval ==
    "split"``), else one draw of the training view sampler in a window of ``eval_span``
    frames (procedural paths are short, so every-8th targets would be far from every input)
    from the generator of entropy ``(seed, 7, i)``, or ``(7, i)`` without
    ``eval_views_follow_seed``."""
    data = exp.data
    if data.procedural_eval == "split":
        inputs, targets, _ = held_out_split(data, stage.num_inputs, scene)
        return inputs, targets
    rng = np.random.default_rng([exp.seed, 7, i] if data.eval_views_follow_seed else [7, i])
    return training_views(
        rng, len(scene), stage.num_inputs, stage.num_targets, data.eval_span, data.eval_span, input_weight=0.0
    )


def eval_samples(exp: ExperimentConfig, stage: StageConfig) -> tuple[list[dict[str, np.ndarray]], list[str]]:
    """The held-out samples of ``stage`` (``make_sample`` layout, no batch axis) and their
    scene names, deterministic: the first ``data.num_eval_scenes`` scenes of
    :func:`scene_source` (held out), at the stage's view counts and geometry (no zoom).
    Real scenes: the paper protocol (:func:`held_out_split`, printing per scene what it
    used); procedural: :func:`_procedural_views`."""
    data = exp.data
    source = scene_source(data, held_out=True)
    geom = view_geometry(stage, exp.model.size_multiple, train=False)
    with_depth = needs_depth(exp)
    index = formats.read_kmeans_index(data.eval_index) if data.eval_index else None
    samples, names = [], []
    for i in range(min(data.num_eval_scenes, len(source))):
        scene = source.load(i)
        if data.kind == "procedural":
            inputs, targets = _procedural_views(exp, stage, i, scene)
        else:
            inputs, targets, how = held_out_split(data, stage.num_inputs, scene, source.paths[i], index)  # pyright: ignore[reportAttributeAccessIssue] -- the source made here is a FileSource (a HeldOutSource for .base), which has it
        samples.append(make_sample(scene, inputs, targets, geom, rng=None, with_depth=with_depth, rescale=data.rescale))
        if data.kind != "procedural":
            h, w = samples[-1]["input_images"].shape[-3:-1]
            print(f"eval scene {scene.name}: {len(inputs)} inputs, {len(targets)} targets, views {h}x{w} (HxW); {how}")
        names.append(scene.name)
    return samples, names
