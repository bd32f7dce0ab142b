"""Fixed-shape, deterministic, prefetched training batches.

**The batch layout** (the one place it is defined; the model consumes exactly this dict of
NumPy arrays, after Long-LRM scene normalisation computed from the input cameras):

=====================  =====================  ==========================================
key                    shape                  content
=====================  =====================  ==========================================
``input_images``       ``[B, V, H, W, 3]``    float32 RGB in [0, 1]
``input_c2w``          ``[B, V, 4, 4]``       float32 OpenCV camera-to-world
``input_intrinsics``   ``[B, V, 4]``          float32 ``(fx, fy, cx, cy)`` in pixels
``target_images``      ``[B, T, H, W, 3]``    float32 RGB in [0, 1]
``target_c2w``         ``[B, T, 4, 4]``       float32
``target_intrinsics``  ``[B, T, 4]``          float32
``target_depth``       ``[B, T, H, W]``       float32 z-depth in normalised scene units
                                              (metres times the scene scale); 0 = invalid.
                                              Only with ``BatchConfig.with_depth``.
``scene_scale``        ``[B]``                float32 normalised units per metre (world
                                              unit): divide depths by it for metres.
=====================  =====================  ==========================================

Determinism: batch ``step`` is a pure function of ``(seed, step)``: element ``b`` of the
*global* batch draws its scene, views and augmentation from ``default_rng([seed, step, b,
attempt])``. A resumed run that restarts at ``start_step`` therefore sees the same batches,
whatever the number of workers. Each process builds only its slice of the global batch
(``process_index`` of ``process_count``), sized to split evenly over its local devices.

Bad scenes (missing or corrupt files, bad poses, too few frames) are skipped: the element
retries with the next ``attempt`` (a different scene), a warning is issued and
``iterator.skipped`` counts it. Only ``max_attempts`` consecutive failures raise.
"""

from __future__ import annotations

import collections
import multiprocessing
import threading
import warnings
from collections.abc import Callable, Iterator, Sequence
from concurrent.futures import Future, ProcessPoolExecutor, ThreadPoolExecutor
from dataclasses import dataclass, field
from typing import Protocol, runtime_checkable

import numpy as np

from llrmpp_jax.data.preprocess import ViewGeometry, make_sample
from llrmpp_jax.data.scene import Scene
from llrmpp_jax.data.selection import training_views
from llrmpp_jax.data.synthetic import ProceduralConfig, procedural_scene
from llrmpp_jax.errors import UserError


@runtime_checkable  # so the annotation can be checked (tests run beartype on the package)
class SceneSource(Protocol):
    """Indexable collection of scenes: ``len(source)`` and ``source.load(i) -> Scene``."""

    def __len__(self) -> int: ...

    def load(self, index: int) -> Scene: ...


@dataclass(frozen=True)
class ProceduralSource:
    """Endless procedural scenes: index i is the scene of seed i."""

    config: ProceduralConfig = field(default_factory=ProceduralConfig)  # pyright: ignore[reportArgumentType, reportCallIssue] -- a frozen dataclass as default_factory: pyright misreads the field overloads
    size: int = 2**31 - 1

    def __len__(self) -> int:
        return self.size

    def load(self, index: int) -> Scene:
        return procedural_scene(index, self.config)


@dataclass(frozen=True)
class FileSource:
    """Scenes on disk: ``reader(paths[i])``, e.g. ``FileSource(paths, read_long_lrm_scene)``."""

    paths: Sequence[str]
    reader: Callable[[str], Scene]

    def __len__(self) -> int:
        return len(self.paths)

    def load(self, index: int) -> Scene:
        return self.reader(self.paths[index])


@dataclass(frozen=True)
class BatchConfig:
    """Global batch size, view counts, frame-window and image geometry.

    ``min_span`` / ``max_span``: training window length in frames (None = whole scene;
    Long-LRM stages 1-2 use 64-128). ``input_weight``: target-draw weight of input frames
    (Long-LRM++: 0.1). ``reverse_prob`` / ``shuffle_prob``: Long-LRM's input-order
    augmentations (0.5 each in its configs; 0 = keep the sorted order).
    ``scene_scale``: Long-LRM's ``data.scene_scale``; ``rescale`` False keeps world units
    (:func:`~llrmpp_jax.geometry.normalize_scene`: one depth scale across windows).
    """

    global_batch: int
    num_inputs: int
    num_targets: int
    geometry: ViewGeometry = field(default_factory=ViewGeometry)
    min_span: int | None = None
    max_span: int | None = None
    input_weight: float = 0.1
    reverse_prob: float = 0.0
    shuffle_prob: float = 0.0
    with_depth: bool = False
    scene_scale: float = 1.0
    rescale: bool = True
    max_attempts: int = 16


def build_sample(source: SceneSource, cfg: BatchConfig, rng: np.random.Generator) -> dict[str, np.ndarray]:
    """One training sample drawn with ``rng``: a scene, a view split, an augmentation."""
    scene = source.load(int(rng.integers(len(source))))
    inputs, targets = training_views(
        rng, len(scene), cfg.num_inputs, cfg.num_targets, cfg.min_span, cfg.max_span, cfg.input_weight
    )
    # Draw only for enabled augmentations, so the default stream does not depend on them.
    if cfg.reverse_prob > 0 and rng.random() < cfg.reverse_prob:
        inputs = inputs[::-1]
    if cfg.shuffle_prob > 0 and rng.random() < cfg.shuffle_prob:
        inputs = rng.permutation(inputs)
    return make_sample(
        scene,
        inputs,
        targets,
        cfg.geometry,
        rng=rng,
        with_depth=cfg.with_depth,
        scene_scale=cfg.scene_scale,
        rescale=cfg.rescale,
    )


def build_element(
    source: SceneSource, cfg: BatchConfig, seed: int, step: int, b: int
) -> tuple[dict[str, np.ndarray], list[str]]:
    """Element ``b`` of the global batch of ``step``: ``(sample, skipped)``, ``skipped`` one
    line per bad scene passed over before it (each retry draws another scene). Raises
    ``RuntimeError`` after ``cfg.max_attempts`` bad scenes in a row."""
    skipped, error = [], None
    for attempt in range(cfg.max_attempts):
        rng = np.random.default_rng([seed, step, b, attempt])
        try:
            return build_sample(source, cfg, rng), skipped
        except (OSError, ValueError) as e:
            error = e
            skipped.append(f"data: skipped a scene (step {step}, element {b}, attempt {attempt}): {e}")
    raise RuntimeError(
        f"data: {cfg.max_attempts} scenes in a row failed for step {step}, element {b}; last error: {error}"
    )


_PROCESS_DATA: tuple[SceneSource, BatchConfig] | None = None  # a worker process's source and cfg


def _init_process(source: SceneSource, cfg: BatchConfig) -> None:
    global _PROCESS_DATA
    _PROCESS_DATA = source, cfg
    # A worker only builds NumPy samples: keep JAX (imported with the readers) off the accelerator.
    import jax

    jax.config.update("jax_platforms", "cpu")


def _process_element(seed: int, step: int, b: int) -> tuple[dict[str, np.ndarray], list[str]]:
    return build_element(*_PROCESS_DATA, seed, step, b)  # pyright: ignore[reportCallIssue] -- the unpacked tuple holds the other arguments


class BatchIterator:
    """Iterator of fixed-shape batches (see the module docstring for the layout).

    Args:
      source: where scenes come from. cfg: what a batch holds. seed: the run's data seed.
      start_step: first step to produce (resume from ``state()["step"]`` of a checkpoint).
      num_devices: local devices the local batch must split over evenly.
      process_index, process_count: this host's slice of the global batch.
      num_workers: background threads building batches, or with ``worker_processes`` processes
        building batch elements (the source and ``cfg`` must pickle). prefetch: batches kept
        in flight. NumPy ray casting and image decoding hold the GIL for most of a sample, so
        threads do not go past about one core; processes do, for a many-core host feeding an
        accelerator.
    """

    def __init__(
        self,
        source: SceneSource,
        cfg: BatchConfig,
        seed: int,
        start_step: int = 0,
        num_devices: int = 1,
        process_index: int = 0,
        process_count: int = 1,
        num_workers: int = 2,
        prefetch: int = 2,
        worker_processes: bool = False,
    ):
        if cfg.global_batch % process_count:
            raise UserError(f"global_batch {cfg.global_batch} does not split over {process_count} processes")
        local = cfg.global_batch // process_count
        if local % num_devices:
            raise UserError(
                f"local batch {local} (global {cfg.global_batch} / {process_count} processes) "
                f"does not split over {num_devices} devices"
            )
        if len(source) < 1:
            raise UserError("BatchIterator: the scene source is empty")
        if seed < 0 or start_step < 0:
            raise UserError(f"BatchIterator: seed and start_step must be >= 0, got {seed}, {start_step}")
        self.source, self.cfg, self.seed = source, cfg, int(seed)
        self.local_batch = local
        self.offset = process_index * local
        self.step = int(start_step)
        self.skipped = 0
        self._lock = threading.Lock()
        self._prefetch = max(1, prefetch)
        self._processes = None
        if worker_processes:
            # spawn, not fork: the parent runs JAX's threads, which a fork would copy mid-state
            self._processes = ProcessPoolExecutor(
                max(1, num_workers),
                mp_context=multiprocessing.get_context("spawn"),
                initializer=_init_process,
                initargs=(source, cfg),
            )
        # with processes, the threads only gather elements: one per batch in flight
        threads = self._prefetch + 1 if worker_processes else max(1, num_workers)
        self._pool = ThreadPoolExecutor(max_workers=threads)
        self._pending: collections.deque[tuple[int, Future]] = collections.deque()

    def state(self) -> dict[str, int]:
        """Checkpointable position: ``{"seed", "step"}`` of the next batch to be returned."""
        return {"seed": self.seed, "step": self.step}

    def batch_at(self, step: int) -> dict[str, np.ndarray]:
        """The local batch of ``step`` (pure in ``(seed, step)``; safe from any thread)."""
        elements = range(self.offset, self.offset + self.local_batch)
        if self._processes is None:
            results = [build_element(self.source, self.cfg, self.seed, step, b) for b in elements]
        else:
            futures = [self._processes.submit(_process_element, self.seed, step, b) for b in elements]
            results = [f.result() for f in futures]
        messages = [m for _, skipped in results for m in skipped]
        with self._lock:
            self.skipped += len(messages)
        for message in messages:
            warnings.warn(message, stacklevel=2)
        return {k: np.stack([s[k] for s, _ in results]) for k in results[0][0]}

    def __iter__(self) -> Iterator[dict[str, np.ndarray]]:
        return self

    def __next__(self) -> dict[str, np.ndarray]:
        # Keep `prefetch` later batches building while the caller works on this one.
        while len(self._pending) < self._prefetch + 1:
            nxt = self._pending[-1][0] + 1 if self._pending else self.step
            self._pending.append((nxt, self._pool.submit(self.batch_at, nxt)))
        step, fut = self._pending.popleft()
        batch = fut.result()
        self.step = step + 1
        return batch

    def close(self) -> None:
        """Stop the workers (pending batches are dropped)."""
        for _, fut in self._pending:
            fut.cancel()
        self._pending.clear()
        self._pool.shutdown(wait=True, cancel_futures=True)
        if self._processes is not None:
            self._processes.shutdown(wait=True, cancel_futures=True)

    def __enter__(self) -> BatchIterator:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
