"""The scales an ablation table runs at (``"smoke"``, ``"cpu"``, ``"paper"``): everything
about a run that is not the architecture (:class:`Scale`), the base models, the environment
overrides (``LLRMPP_NOTEBOOK_STEPS`` / ``_SEEDS`` / ``_WORKERS`` / ``_SCALE``) and the
procedural data's seeds and units. The package docstring describes each scale."""

from __future__ import annotations

import dataclasses
import os
from dataclasses import dataclass, replace

from llrmpp_jax import config as C
from llrmpp_jax.experiment import load_experiment

TRAIN_SCENES = 100_000  # training seeds are [0, TRAIN_SCENES)
EVAL_SEED = 1_000_000  # held-out seeds start here (disjoint from training)
SCALES = ("smoke", "cpu", "paper")
CPU_STEPS = 400  # the cpu scale's budget, from the pilot (notebooks/README.md)
CPU_MAX_SEEDS = 10  # the cpu scale adds seeds to an unresolved ordering up to this many ...
CPU_BUDGET_MIN = 90.0  # ... within this many minutes per table
# The cpu scale's peak learning rate: at 2e-3 the gradient norm bursts right after the warmup,
# and an update that passes the spike guard can break a seed's model, which then ends below
# its siblings; at 1e-3 that seed trains like the others and a healthy one loses nothing
# (notebooks/README.md, "Stalled seeds").
CPU_LR = 1e-3
CPU_WORKERS = 4  # at most this many single-core trainings at once at the cpu scale (memory)
# Every table at the smoke and cpu scales keeps the procedural rooms' world units
# (Scale.rescale False). Long-LRM's per-window rescaling (input cameras into [-1, 1]^3) gives
# the cpu scale's short windows depth scales that differ several-fold, and at that spread the
# depth head learned nothing; in world units they differ little (notebooks/README.md, "Depth
# at this scale"). Where the depth head starts (DecoderConfig.depth_bias, depth tables): the
# mean log target depth of those windows in world units (about 2.9 units), estimated over
# draws of 128 samples.
PROCEDURAL_DEPTH_BIAS = 1.05
# The Gaussian head's distance range in those world units (GaussianHeadConfig.max_dist; the
# cpu base's 3 was chosen on rescaled rooms, where 57% of the target depths lie beyond it):
# 99% of the training windows' target pixels lie within 10 units along their rays (z-depth
# 99th percentile 7.2, corner rays 1.41x longer at this field of view). With 3, 54% of the
# held-out depths were out of the colour Gaussians' reach, and Table 7's colour row could not
# place them: its depth error was the same for every seed.
PROCEDURAL_MAX_DIST = 10.0


@dataclass(frozen=True)
class Scale:
    """Everything about a run that is not the architecture.

    ``width_divisor`` shrinks the paper's layer widths (decoder E) at the small scales so a
    row like "E = 768" stays 3x its "E = 256" sibling. ``frames`` is the length of each
    procedural camera path; training windows (``min_span``..``max_span`` frames, None = the
    whole path) and the evaluation views (:func:`eval_samples`, ``eval_span``) are drawn
    from it. ``seeds``: every row is trained once per seed ``0..seeds-1``
    (model init and data order). ``workers``: how many (row, seed) trainings run at once,
    each in its own process pinned to one CPU core (1: one after another in this process,
    on every core). On small models a CPU core is used better by its own training than by
    XLA's threads inside one step (:func:`run_table`); a worker holds ~1.5 GB.
    """

    name: str
    base: C.ModelConfig
    size: int  # square images, H = W (pixels)
    num_inputs: int
    num_targets: int
    batch: int  # global batch (scenes per step)
    steps: int
    lr: float
    warmup: int
    perceptual_weight: float
    eval_scenes: int
    frames: int
    lpips: bool
    timing_repeats: int
    width_divisor: int = 1
    seeds: int = 1
    min_span: int | None = None
    max_span: int | None = None
    eval_span: int | None = None
    workers: int = 1
    max_seeds: int = 0  # sequential: add seeds to unresolved orderings up to this many (0: fixed seeds)
    budget_min: float | None = None  # sequential: add no seed after this many minutes of the table
    rescale: bool = True  # Long-LRM's per-window scale normalisation (geometry.normalize_scene)
    # Skip updates whose gradient norm is this many times the recent mean (train/spikes.py):
    # at the small scales the usual norm is ~0.03, far below Long-LRM's absolute guards.
    spike_factor: float | None = 10.0

    def __str__(self) -> str:
        m = self.base
        return (
            f"{self.name}: {self.size}x{self.size}, {self.num_inputs} inputs + {self.num_targets} targets, "
            f"batch {self.batch}, {self.steps} steps (lr {self.lr}), {self.seeds} seed(s) per row, "
            f"{self.eval_scenes} held-out scenes, {self.workers} worker(s); "
            f"backbone D={m.backbone.dims} {m.backbone.pattern!r} x{m.backbone.num_layers}, outputs {m.outputs}"
            + ("" if self.rescale else "; poses not rescaled (world units)")
        )

    def width(self, paper_width: int) -> int:
        """A paper layer width at this scale."""
        return paper_width // self.width_divisor


def smoke_base() -> C.ModelConfig:
    """:func:`~llrmpp_jax.config.tiny` with a Gaussian head for procedural rooms, which
    span a few units: Gaussians start at ``exp(-3)`` ~ 0.05 units rather than
    ``exp(-6.9)`` (visible at 32x32 from the start); :func:`make_scale` sets their distance
    range (:data:`PROCEDURAL_MAX_DIST`)."""
    base = C.tiny()
    return replace(base, head=replace(base.head, scale_bias=-3.0))


def cpu_base() -> C.ModelConfig:
    """The demo model (the ``demo`` recipe), whose recipe was chosen on this kind of
    machine, with the paper's chosen rows: K = 16 Gaussians of
    F = 32 features per token (Table 4) and an ``LLGGG`` decoder of width 256 / 4 with S = 2
    partitions (Tables 5, 6). At 64x64 the K = 16 head gives one Gaussian per half-resolution
    canvas pixel (2x2 image pixels) per input view, the paper's density at 256x256. Each row
    then sets its own K, F, decoder, S.

    The splat buffer holds 16 intersections per Gaussian, every tile of a 64x64 canvas, so
    it cannot overflow at this scale: with the default 8, the colour-Gaussian rows (one
    Gaussian per pixel, grown towards Long-LRM's largest scale within 400 steps) dropped
    thousands of intersections per training step.

    The compositor advances 2 tiles per loop (``tiles_per_group``, default 64): a 64x64
    canvas has only 16 tiles, whose lists differ several-fold in length, and one loop over
    all of them runs as long as the longest, so smaller groups run the splat faster here
    (docs/lab-notes.md, "The ablation scales"). Outputs do not depend on it."""
    base = load_experiment("demo").model
    # The tables were run with the demo's earlier head start (every Gaussian at its patch
    # centre, scale_bias -2.5); the demo's grid start needs a square K, and Table 4 has K = 8, 32.
    head = replace(base.head, gaussians_per_token=16, feature_dim=32, anchors="centre", scale_bias=-2.5)
    return replace(
        base,
        head=head,
        decoder=replace(base.decoder, blocks="LLGGG", dim=64, partitions=2),
        splat=replace(base.splat, intersections_per_gaussian=16.0, tiles_per_group=2),
    )


def _env_int(name: str, minimum: int) -> int | None:
    text = os.environ.get(name)
    if not text:
        return None
    try:
        value = int(text)
    except ValueError:
        raise ValueError(f"{name}={text!r}: expected an integer >= {minimum}") from None
    if value < minimum:
        raise ValueError(f"{name}={text!r}: expected an integer >= {minimum}, got {value}")
    return value


def scale_name() -> str:
    """``LLRMPP_NOTEBOOK_SCALE`` (default ``"smoke"``), checked."""
    name = os.environ.get("LLRMPP_NOTEBOOK_SCALE", "smoke")
    if name not in SCALES:
        raise ValueError(f"LLRMPP_NOTEBOOK_SCALE={name!r}: expected one of {', '.join(SCALES)}")
    return name


def make_scale(
    name: str,
    *,
    paper_views: int,
    depth: bool = False,
    paper_steps: int = 10_000,
    cpu_seeds: int = 3,
    cpu_steps: int = CPU_STEPS,
) -> Scale:
    """The ``"smoke"``, ``"cpu"`` or ``"paper"`` scale of a table whose paper setting has
    ``paper_views`` input views at 256x256 (``depth``: ScanNet-style colour + depth).
    ``cpu_seeds``: seeds per row at the cpu scale (3; a table whose rows are cheap enough
    runs more within the hour, for narrower intervals). ``cpu_steps``: training steps at
    the cpu scale (:data:`CPU_STEPS`; a table whose chosen row needs longer to clear the
    baselines, as depth does, sets its own)."""
    if cpu_seeds < 1:
        raise ValueError(f"make_scale: cpu_seeds must be >= 1, got {cpu_seeds}")
    if cpu_steps < 1:
        raise ValueError(f"make_scale: cpu_steps must be >= 1, got {cpu_steps}")
    if name == "smoke":
        scale = Scale(
            name="smoke",
            base=smoke_base(),
            size=32,
            num_inputs=2,
            num_targets=2,
            batch=2,
            steps=40,
            lr=2e-3,
            warmup=10,
            perceptual_weight=0.0,
            eval_scenes=4,
            frames=16,
            lpips=False,
            timing_repeats=3,
            width_divisor=4,
        )
    elif name == "cpu":
        scale = Scale(
            name="cpu",
            base=cpu_base(),
            size=64,
            num_inputs=4,
            num_targets=2,
            batch=2,
            steps=cpu_steps,
            lr=CPU_LR,
            warmup=50,
            perceptual_weight=0.0,
            eval_scenes=16,
            frames=16,
            lpips=True,
            timing_repeats=3,
            width_divisor=4,
            seeds=cpu_seeds,
            min_span=6,
            max_span=10,
            eval_span=8,
            max_seeds=CPU_MAX_SEEDS,
            budget_min=CPU_BUDGET_MIN,
            workers=min(CPU_WORKERS, len(os.sched_getaffinity(0))),
        )
    elif name == "paper":
        base = C.paper_scannet() if depth else C.paper_dl3dv()
        scale = Scale(
            name="paper",
            base=base,
            size=256,
            num_inputs=paper_views,
            num_targets=8,
            batch=8,
            steps=paper_steps,
            lr=4e-4,
            warmup=min(2000, paper_steps // 10),
            perceptual_weight=0.5,
            eval_scenes=64,
            frames=max(64, 2 * paper_views + 16),
            lpips=True,
            timing_repeats=10,
            seeds=3,
        )
    else:
        raise ValueError(f"make_scale: name must be one of {', '.join(SCALES)}, got {name!r}")
    if name != "paper":  # the paper scale keeps its data's normalisation, range and depth_bias
        base = replace(scale.base, head=replace(scale.base.head, max_dist=PROCEDURAL_MAX_DIST))
        if depth:
            base = replace(base, decoder=replace(base.decoder, depth_bias=PROCEDURAL_DEPTH_BIAS))
        scale = dataclasses.replace(scale, base=base, rescale=False)
    if depth:
        scale = dataclasses.replace(scale, base=replace(scale.base, outputs=("rgb", "depth")))
    steps = _env_int("LLRMPP_NOTEBOOK_STEPS", 0)
    if steps is not None:
        scale = dataclasses.replace(scale, steps=steps, warmup=min(scale.warmup, steps))
    seeds = _env_int("LLRMPP_NOTEBOOK_SEEDS", 1)
    if seeds is not None:
        scale = dataclasses.replace(scale, seeds=seeds)
    workers = _env_int("LLRMPP_NOTEBOOK_WORKERS", 1)
    if workers is not None:
        scale = dataclasses.replace(scale, workers=workers)
    max_seeds = _env_int("LLRMPP_NOTEBOOK_MAX_SEEDS", 0)
    if max_seeds is not None:
        scale = dataclasses.replace(scale, max_seeds=max_seeds)
    budget = _env_int("LLRMPP_NOTEBOOK_BUDGET_MIN", 1)
    if budget is not None:
        scale = dataclasses.replace(scale, budget_min=float(budget))
    return scale
