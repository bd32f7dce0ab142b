"""Which frames of a scene become input views and which become targets.

* Evaluation (paper §4, Long-LRM ``data_eval``): targets are every ``every``-th frame from
  index 0; inputs come from the remaining frames by k-means on ``[camera position, forward
  axis]`` (raw world coordinates), taking the frame nearest each cluster centre.
* Training (Long-LRM ``__getitem__`` + Long-LRM++ appendix): a random window of
  consecutive frames; inputs spread uniformly over it; targets drawn from the window
  without replacement, input frames having weight ``input_weight`` (0.1) and others 1.

Everything is deterministic: k-means uses a fixed seed, training draws take a generator.
"""

from __future__ import annotations

import numpy as np

from llrmpp_jax.array_typing import Float, Int


def every_nth(num_frames: int, every: int = 8) -> Int[np.ndarray, "T"]:
    """Frame indices ``0, every, 2*every, ...`` below ``num_frames``."""
    if every < 1 or num_frames < 1:
        raise ValueError(f"every_nth: need num_frames >= 1 and every >= 1, got {num_frames}, {every}")
    return np.arange(0, num_frames, every, dtype=np.int64)


def kmeans(
    points: Float[np.ndarray, "P D"], k: int, seed: int = 0, iterations: int = 100
) -> Float[np.ndarray, "k D"]:
    """Lloyd's k-means with k-means++ seeding from ``default_rng(seed)``; a cluster that
    empties is re-seeded at the point farthest from its centre. Deterministic."""
    points = np.asarray(points, dtype=np.float64)
    p = points.shape[0]
    if not 1 <= k <= p:
        raise ValueError(f"kmeans: need 1 <= k <= number of points ({p}), got k={k}")
    rng = np.random.default_rng(seed)
    centres = [points[rng.integers(p)]]
    d2 = ((points - centres[0]) ** 2).sum(axis=1)
    for _ in range(1, k):
        total = d2.sum()
        j = int(rng.choice(p, p=d2 / total)) if total > 0 else int(rng.integers(p))
        centres.append(points[j])
        d2 = np.minimum(d2, ((points - points[j]) ** 2).sum(axis=1))
    centres = np.array(centres)
    for _ in range(iterations):
        dist = ((points[:, None, :] - centres[None, :, :]) ** 2).sum(axis=2)
        label = np.argmin(dist, axis=1)
        new = centres.copy()
        for c in range(k):
            members = points[label == c]
            if len(members):
                new[c] = members.mean(axis=0)
            else:
                new[c] = points[int(np.argmax(dist[np.arange(p), label]))]
        if np.array_equal(new, centres):
            break
        centres = new
    return centres


def kmeans_inputs(
    c2w: Float[np.ndarray, "N 4 4"], candidates: Int[np.ndarray, "C"], num_inputs: int, seed: int = 0
) -> Int[np.ndarray, "V"]:
    """``num_inputs`` distinct frames from ``candidates``, sorted: k-means on
    ``[c2w[:3, 3], c2w[:3, 2]]`` of the candidates, then for each centre (in order of how
    close its best frame is) the nearest candidate not already taken."""
    candidates = np.asarray(candidates, dtype=np.int64)
    if len(candidates) < num_inputs:
        raise ValueError(
            f"kmeans_inputs: {num_inputs} input views requested but only {len(candidates)} candidate frames"
        )
    feats = np.concatenate([c2w[candidates, :3, 3], c2w[candidates, :3, 2]], axis=1)
    centres = kmeans(feats, num_inputs, seed=seed)
    dist = ((feats[None, :, :] - centres[:, None, :]) ** 2).sum(axis=2)  # [k, C]
    taken = np.zeros(len(candidates), dtype=bool)
    chosen = []
    for c in np.argsort(dist.min(axis=1), kind="stable"):
        order = np.argsort(dist[c], kind="stable")
        j = int(order[np.argmax(~taken[order])])
        taken[j] = True
        chosen.append(candidates[j])
    return np.sort(np.array(chosen, dtype=np.int64))


def eval_views(
    c2w: Float[np.ndarray, "N 4 4"], num_inputs: int, every: int = 8, max_frames: int | None = None
) -> tuple[Int[np.ndarray, "V"], Int[np.ndarray, "T"]]:
    """Paper evaluation split ``(inputs, targets)``: targets every ``every``-th frame,
    inputs by :func:`kmeans_inputs` over the rest (optionally only the first ``max_frames``
    frames, as the ScanNet protocol uses the first 1280)."""
    n = c2w.shape[0] if max_frames is None else min(max_frames, c2w.shape[0])
    targets = every_nth(n, every)
    rest = np.setdiff1d(np.arange(n), targets)
    return kmeans_inputs(c2w, rest, num_inputs), targets


def uniform_inputs(num_frames: int, num_inputs: int) -> Int[np.ndarray, "V"]:
    """``num_inputs`` distinct frames spread evenly over ``num_frames`` (ends included;
    truncated like Long-LRM's ``np.linspace(..., dtype=int)``), as the ScanNet protocol
    takes its 128 inputs."""
    if not 1 <= num_inputs <= num_frames:
        raise ValueError(f"uniform_inputs: {num_inputs} views requested from {num_frames} frames")
    return np.linspace(0, num_frames - 1, num_inputs).astype(np.int64)


def training_views(
    rng: np.random.Generator,
    num_frames: int,
    num_inputs: int,
    num_targets: int,
    min_span: int | None = None,
    max_span: int | None = None,
    input_weight: float = 0.1,
) -> tuple[Int[np.ndarray, "V"], Int[np.ndarray, "T"]]:
    """One training draw ``(inputs, targets)`` of distinct sorted indices each.

    A window of ``span + 1`` consecutive frames, ``span`` uniform in ``[min_span,
    max_span]`` (clipped to the scene; default: the whole scene), starts at a uniform
    offset. Inputs are ``num_inputs`` evenly spread frames of the window. Targets are drawn
    from the window without replacement with weight ``input_weight`` for input frames and
    1 for the rest (so targets mostly avoid inputs but may include them).
    """
    if num_inputs < 1 or num_targets < 1:
        raise ValueError(f"training_views: need at least one input and one target, got {num_inputs}, {num_targets}")
    need = max(num_inputs, num_targets)
    if num_frames < need:
        raise ValueError(
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
