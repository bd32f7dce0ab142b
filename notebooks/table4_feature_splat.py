# %% [markdown]
# # Table 4: feature-Gaussian hyperparameters (K, F, canvas size)
#
# Paper Table 4 (`tb:featsplat`): Gaussians per token K, Gaussian feature width F and the
# feature-splat canvas size as a fraction of the image (1/r), on DL3DV-140 with 4 input
# views at 256x256 and the `LLG` decoder. Rows: (K, F, canvas) = (8, 32, 0.5),
# (8, 64, 0.5), (16, 32, 0.25), **(16, 32, 0.5) (chosen)**, (16, 32, 1.0), (16, 64, 0.5),
# (32, 16, 0.5); the paper reports PSNR.
#
# Every row is trained briefly on procedural scenes and scored on held-out ones.
# `SCALE = "smoke"` runs a tiny backbone on a CPU (numbers only show that the pipeline
# works); `SCALE = "paper"` uses the paper's model at 256x256 (accelerators). K, F and r
# are the paper's values at both scales. A smoke run compiles every row (~1 minute each on
# a 2-core CPU), so it takes several minutes; `LLRMPP_NOTEBOOK_ROWS=0,3` (row indices)
# runs a subset.

# %%
import os

import _ablation as A
from llrmpp_jax import config as C

SCALE = os.environ.get("LLRMPP_NOTEBOOK_SCALE", "smoke")  # "smoke" (CPU) or "paper" (accelerators)

scale = A.make_scale(SCALE, paper_views=4)
print(scale)

# %% [markdown]
# One config per row: the scale's base model with an `LLG` decoder (E = 256, divided by
# `scale.width_divisor` in smoke mode), K Gaussians per token of F features, and canvas
# ratio r = 1 / canvas size. The paper's PSNR is copied from the .tex.


# %%
def feature_splat(k: int, f: int, canvas: float):
    return lambda base: C.replace(
        base,
        head=C.replace(base.head, gaussians_per_token=k, feature_dim=f),
        decoder=C.replace(base.decoder, blocks="LLG", dim=scale.width(256), canvas_ratio=round(1 / canvas)),
    )


ROWS = [  # (K, F, canvas size, paper PSNR, chosen)
    (8, 32, 0.5, "27.94", False),
    (8, 64, 0.5, "28.20", False),
    (16, 32, 0.25, "27.81", False),
    (16, 32, 0.5, "28.37", True),
    (16, 32, 1.0, "28.41", False),
    (16, 64, 0.5, "28.44", False),
    (32, 16, 0.5, "26.71", False),
]
VARIANTS = [
    A.Variant({"K": str(k), "F": str(f), "canvas": str(c)}, feature_splat(k, f, c), {"PSNR": psnr}, chosen=chosen)
    for k, f, c, psnr, chosen in ROWS
]

# %%
results = A.run_table(VARIANTS, scale)

# %% [markdown]
# Ours (held-out procedural scenes) next to the paper's PSNR, with the Gaussians per scene,
# parameter count and timings of each row.

# %%
print(A.format_table(results, ["K", "F", "canvas"], [
    A.Column("psnr", "PSNR"), A.Column("paper:PSNR", "paper PSNR"),
    A.Column("ssim", "SSIM", 3), A.Column("lpips", "LPIPS", 3),
    A.Column("gaussians", "Gaussians"), A.Column("params", "params"),
    A.Column("recon_s", "recon ms", 1, 1000.0), A.Column("render_s", "render ms/frame", 1, 1000.0),
]))
