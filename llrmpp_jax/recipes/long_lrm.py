"""Long-LRM (the predecessor, colour Gaussians): the paper architecture of the official
checkpoint, so a PyTorch checkpoint converts and runs with no config of your own.

Convert:      llrmpp convert --checkpoint checkpoint_000010000.pt --out runs/long_lrm_params
Reconstruct:  llrmpp reconstruct --checkpoint runs/long_lrm_params --scene data/fox --out fox.gs
Train:        llrmpp train --config long_lrm --data PATH --workdir runs/long_lrm

Architecture (reference facts §1.1, ``configs/7m1t_tm.yaml``): 24 blocks ``mmmmmmmt``, dims
[256, 1024] with the token merge before block 8, patch 8 (16 after the merge), no QK-norm,
one SH-degree-3 Gaussian per pixel, white background. Stages follow Long-LRM's DL3DV recipe
(facts §2): 256² square crops, then 512² square crops, then full 960x540 frames, 32 inputs
and 8 targets throughout.
"""

from llrmpp_jax import config as C
from llrmpp_jax.experiment import DataConfig, ExperimentConfig, StageConfig

DATA = "data/dl3dv/train.txt"  # Long-LRM .txt index of scene JSONs (or any capture folder via --data)
EVAL = "data/dl3dv/dl3dv140.txt"


def get_config() -> ExperimentConfig:
    stages = (
        StageConfig("stage1_256", steps=60_000, global_batch=256, num_inputs=32, num_targets=8,
                    resize_h=256, square_crop=True, lr=4e-4, warmup_steps=2000, min_span=64, max_span=128),
        StageConfig("stage2_512", steps=10_000, global_batch=64, num_inputs=32, num_targets=8,
                    resize_h=512, square_crop=True, lr=4e-5, warmup_steps=0, min_span=64, max_span=128),
        StageConfig("stage3_540", steps=10_000, global_batch=64, num_inputs=32, num_targets=8,
                    resize_h=540, lr=4e-5, warmup_steps=0),
    )
    return ExperimentConfig(
        name="long_lrm", model=C.long_lrm(), stages=stages,
        data=DataConfig(kind="long_lrm", path=DATA, eval_path=EVAL, num_eval_scenes=140, workers=8),
        perceptual_weight=0.5, bf16=True, log_every=50, eval_every=2000, checkpoint_every=1000,
    )
