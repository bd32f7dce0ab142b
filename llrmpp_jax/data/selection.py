"""Which frames of a scene become input views and which become targets.

* Evaluation, DL3DV (paper §4, Long-LRM ``data_eval``): targets are every ``every``-th
  frame from index 0; inputs come from the remaining frames by Long-LRM's k-means
  (:func:`kmeans_inputs`: scikit-learn on ``[camera position, forward axis]`` in raw world
  coordinates, the frame nearest each centre) unless the dataset caches them.
* Evaluation, ScanNetv2 (paper §4.3): the first 1,280 frames, targets every 8th, 128
  inputs spread uniformly (Long-LRM's ``np.linspace`` rule) over the remaining frames.
* Training (Long-LRM ``__getitem__`` + Long-LRM++ appendix): a random window of
  consecutive frames; inputs spread uniformly over it; targets drawn from the window
  without replacement, input frames having weight ``input_weight`` (0.1) and others 1.

Everything is deterministic: k-means uses a fixed seed, training draws take a generator.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from llrmpp_jax.array_typing import Float, Int
from llrmpp_jax.errors import UserError


def every_nth(num_frames: int, every: int = 8) -> Int[np.ndarray, " T"]:
    """Frame indices ``0, every, 2*every, ...`` below ``num_frames``."""
    if every < 1 or num_frames < 1:
        raise UserError(f"every_nth: need num_frames >= 1 and every >= 1, got {num_frames}, {every}")
    return np.arange(0, num_frames, every, dtype=np.int64)


def kmeans_inputs(
    c2w: Float[np.ndarray, "frames 4 4"], candidates: Int[np.ndarray, " candidates"], num_inputs: int
) -> Int[np.ndarray, " V"]:
    """Long-LRM's k-means input selection, exactly as its ``Dataset.__getitem__``: the 6-D
    features ``[c2w[:3, 3], c2w[:3, 2]]`` of the candidates (raw world coordinates),
    ``sklearn.cluster.KMeans(num_inputs, random_state=0, n_init="auto")``, and for each
    centre the candidate nearest to it (first on ties). Returned sorted; two centres with
    the same nearest frame give it twice (Long-LRM does not de-duplicate)."""
    from sklearn.cluster import KMeans  # imported here: ~1 s, and only evaluation needs it

    candidates = np.asarray(candidates, dtype=np.int64)
    if len(candidates) < num_inputs:
        raise UserError(
            f"kmeans_inputs: {num_inputs} input views requested but only {len(candidates)} candidate frames"
        )
    feats = np.concatenate([c2w[candidates, :3, 3], c2w[candidates, :3, 2]], axis=1)
    centres = KMeans(n_clusters=num_inputs, random_state=0, n_init="auto").fit(feats).cluster_centers_
    nearest = [int(np.argmin(np.linalg.norm(feats - c, axis=1))) for c in centres]
    return np.sort(candidates[nearest])


def eval_views(
    c2w: Float[np.ndarray, "frames 4 4"],
    num_inputs: int,
    every: int = 8,
    max_frames: int | None = None,
    inputs: str = "kmeans",
) -> tuple[Int[np.ndarray, " V"], Int[np.ndarray, " T"]]:
    """Paper evaluation split ``(inputs, targets)`` over the first ``max_frames`` frames
    (None: all): targets every ``every``-th frame, inputs from the rest by
    :func:`kmeans_inputs` (``inputs="kmeans"``, DL3DV) or :func:`uniform_inputs`
    (``"uniform"``, ScanNetv2 with ``max_frames=1280``)."""
    if inputs not in ("kmeans", "uniform"):
        raise UserError(f"eval_views: inputs must be 'kmeans' or 'uniform', got {inputs!r}")
    n = c2w.shape[0] if max_frames is None else min(max_frames, c2w.shape[0])
    targets = every_nth(n, every)
    rest = np.setdiff1d(np.arange(n), targets)
    if inputs == "kmeans":
        return kmeans_inputs(c2w, rest, num_inputs), targets
    if len(rest) < num_inputs:
        raise UserError(f"eval_views: {num_inputs} input views requested but only {len(rest)} non-target frames")
    return rest[uniform_inputs(len(rest), num_inputs)], targets


def checked_inputs(indices: Sequence[int], num_frames: int, num_inputs: int, source: str) -> Int[np.ndarray, " V"]:
    """Precomputed input indices (e.g. Long-LRM's cached k-means ones) as sorted int64;
    ``ValueError`` (one line naming ``source``) unless they are ``num_inputs`` integers in
    ``[0, num_frames)``."""
    idx = np.asarray(indices)
    if idx.shape != (num_inputs,) or not np.issubdtype(idx.dtype, np.integer):
        raise UserError(f"{source} must be {num_inputs} integer frame indices, got {list(np.ravel(idx))[:6]}...")
    bad = idx[(idx < 0) | (idx >= num_frames)]
    if bad.size:
        raise UserError(f"{source} holds frame index {int(bad[0])}, out of range for a scene of {num_frames} frames")
    return np.sort(idx.astype(np.int64))


def uniform_inputs(num_frames: int, num_inputs: int) -> Int[np.ndarray, " V"]:
    """``num_inputs`` distinct frames spread evenly over ``num_frames`` (ends included;
    truncated like Long-LRM's ``np.linspace(..., dtype=int)``), as the ScanNet protocol
    takes its 128 inputs."""
    if not 1 <= num_inputs <= num_frames:
        raise UserError(f"uniform_inputs: {num_inputs} views requested from {num_frames} frames")
    return np.linspace(0, num_frames - 1, num_inputs).astype(np.int64)


def training_views(
    rng: np.random.Generator,
    num_frames: int,
    num_inputs: int,
    num_targets: int,
    min_span: int | None = None,
    max_span: int | None = None,
    input_weight: float = 0.1,
) -> tuple[Int[np.ndarray, " V"], Int[np.ndarray, " T"]]:
    """One training draw ``(inputs, targets)`` of distinct sorted indices each.

    A window of ``span + 1`` consecutive frames, ``span`` uniform in ``[min_span,
    max_span]`` (clipped to the scene; default: the whole scene), starts at a uniform
    offset. Inputs are ``num_inputs`` evenly spread frames of the window. Targets are drawn
    from the window without replacement with weight ``input_weight`` for input frames and
    1 for the rest (so targets mostly avoid inputs but may include them).
    """
    if num_inputs < 1 or num_targets < 1:
        raise UserError(f"training_views: need at least one input and one target, got {num_inputs}, {num_targets}")
    need = max(num_inputs, num_targets)
    if num_frames < need:
        raise UserError(
            f"training_views: scene has {num_frames} usable frames, fewer than the {need} views requested "
            f"({num_inputs} inputs, {num_targets} targets)"
        )
    hi = num_frames - 1 if max_span is None else max(need - 1, min(max_span, num_frames - 1))
    lo = max(need - 1, hi if min_span is None else min(min_span, hi))
    span = int(rng.integers(lo, hi + 1))
    start = int(rng.integers(0, num_frames - span))
    window = np.arange(start, start + span + 1)
    inputs = window[uniform_inputs(len(window), num_inputs)]
    weights = np.where(np.isin(window, inputs), input_weight, 1.0)
    targets = rng.choice(window, size=num_targets, replace=False, p=weights / weights.sum())
    return inputs, np.sort(targets)
