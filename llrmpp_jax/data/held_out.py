"""The paper's evaluation split of one held-out scene (:func:`eval_split`): targets every
:data:`~llrmpp_jax.data.sources.EVAL_EVERY` th frame, k-means or uniform inputs over the
other frames, the k-means ones cached in the scene's Long-LRM JSON or in a dataset index
when there are. Which scenes, and how an experiment chooses, is
``llrmpp_jax.experiment_data.eval_samples``."""

from __future__ import annotations

import numpy as np

from llrmpp_jax.data import formats
from llrmpp_jax.data.scene import Scene
from llrmpp_jax.data.selection import checked_inputs, eval_views, every_nth
from llrmpp_jax.data.sources import EVAL_EVERY


def eval_split(
    scene: Scene,
    num_inputs: int,
    inputs: str = "kmeans",
    max_frames: int | None = None,
    json_path: str | None = None,
    index: dict[str, dict] | None = None,
    index_name: str = "the index",
    every: int = EVAL_EVERY,
) -> tuple[np.ndarray, np.ndarray, str]:
    """The paper's evaluation split of one held-out ``scene``: ``(inputs, targets, how)``,
    index arrays ``[num_inputs]`` and ``[T]`` into its frames, and ``how`` a line saying
    what was used.

    Targets are every ``every`` th of the first ``max_frames`` frames (None: all); the
    inputs spread over the others by ``inputs``: ``"uniform"`` (evenly) or ``"kmeans"``,
    read, in this order, from the scene's Long-LRM JSON at ``json_path`` (None: not a
    Long-LRM scene), from the entry of ``scene.name`` in ``index``
    (:func:`~llrmpp_jax.data.formats.read_kmeans_index`; ``index_name`` names it in ``how``
    and errors), else Long-LRM's k-means computed here. Cached inputs cover whole scenes,
    so they are used only when ``max_frames`` is None."""
    n = len(scene)
    if inputs == "uniform":
        chosen, targets = eval_views(scene.c2w, num_inputs, every, max_frames, inputs="uniform")
        first = max_frames is not None and n >= max_frames
        used = max_frames if first else n
        how = (
            f"targets every {every}th of {'the first' if first else 'all'} {used} frames, "
            f"{num_inputs} inputs spread uniformly over the other {used - len(targets)}"  # pyright: ignore[reportOptionalOperand] -- used is max_frames only when it is set
        )
        if max_frames is not None and n < max_frames:
            how = f"only {n} frames, fewer than {max_frames}: {how}"
        return chosen, targets, how
    key = f"fold_{every}_kmeans_{num_inputs}_input"
    if max_frames is None and json_path is not None:
        cached = formats.cached_kmeans_inputs(json_path, every, num_inputs, n)
        if cached is not None:
            return cached, every_nth(n, every), f"inputs: the scene JSON's cached '{key}'"
    if max_frames is None and index is not None and key in index.get(scene.name, {}):
        chosen = checked_inputs(index[scene.name][key], n, num_inputs, f"{index_name}: {scene.name} '{key}'")
        return chosen, every_nth(n, every), f"inputs: '{key}' of {index_name}"
    chosen, targets = eval_views(scene.c2w, num_inputs, every, max_frames, inputs=inputs)
    return chosen, targets, "inputs: Long-LRM's k-means (scikit-learn KMeans, random_state=0, n_init='auto')"
