# %% [markdown]
# # Table 5: splat type and target-frame decoder (blocks, width E)
#
# Paper Table 5 (`tb:decoder`): colour Gaussians splatted directly (Long-LRM style, no
# decoder) against feature Gaussians decoded by blocks of local (`L`, k-NN attention with a
# relative-position bias) and global (`G`) attention, on DL3DV-140 with 4 input views at
# 256x256. Rows: Color; Feature `GGG`, `LLL`, `LLG` (E = 256); **Feature `LLGGG` E = 256
# (chosen)**; Feature `LLGGG` E = 768. The paper reports PSNR.
#
# Every row is trained briefly on procedural scenes and scored on held-out ones.
# `SCALE = "smoke"` runs a tiny backbone on a CPU (numbers only show that the pipeline
# works); `SCALE = "paper"` uses the paper's model at 256x256 (accelerators).
# A smoke run compiles every row (~1 minute each on a 2-core CPU), so it takes a few
# minutes; `LLRMPP_NOTEBOOK_ROWS=0,3` (row indices) runs a subset.

# %%
import os

import _ablation as A
from llrmpp_jax import config as C

SCALE = os.environ.get("LLRMPP_NOTEBOOK_SCALE", "smoke")  # "smoke" (CPU) or "paper" (accelerators)

scale = A.make_scale(SCALE, paper_views=4)
print(scale)

# %% [markdown]
# One config per row. Colour: Long-LRM's head (one Gaussian per pixel, SH degree 3) on the
# same backbone, no decoder. Feature: the scale's base model with the row's decoder
# blocks and width E (divided by `scale.width_divisor` in smoke mode; the `E here` column
# shows the width actually used). `GGG` is the paper's "global attention with absolute
# positional embeddings": its tokens get a fixed 2-D sin-cos embedding of their grid
# coordinates (`absolute_positions`; defined at any canvas size). The rows with `L` blocks
# need none: their relative-position bias carries the geometry. The paper's PSNR is copied
# from the .tex.


# %%
def colour(base: C.ModelConfig) -> C.ModelConfig:
    return C.replace(base, head=C.replace(base.head, mode="color"))


def decoder(blocks: str, dim: int, absolute_positions: bool = False):
    return lambda base: C.replace(base, decoder=C.replace(base.decoder, blocks=blocks, dim=scale.width(dim),
                                                          absolute_positions=absolute_positions))


VARIANTS = [
    A.Variant({"splat": "Color", "blocks": "/", "dim": "/"}, colour, {"PSNR": "27.32"}),
    A.Variant({"splat": "Feature", "blocks": "GGG", "dim": "256"}, decoder("GGG", 256, absolute_positions=True),
              {"PSNR": "27.78"}),
    A.Variant({"splat": "Feature", "blocks": "LLL", "dim": "256"}, decoder("LLL", 256), {"PSNR": "28.23"}),
    A.Variant({"splat": "Feature", "blocks": "LLG", "dim": "256"}, decoder("LLG", 256), {"PSNR": "28.37"}),
    A.Variant({"splat": "Feature", "blocks": "LLGGG", "dim": "256"}, decoder("LLGGG", 256), {"PSNR": "28.74"},
              chosen=True),
    A.Variant({"splat": "Feature", "blocks": "LLGGG", "dim": "768"}, decoder("LLGGG", 768), {"PSNR": "29.09"}),
]

# %%
results = A.run_table(VARIANTS, scale)

# %% [markdown]
# Ours (held-out procedural scenes) next to the paper's PSNR, with the decoder's width and
# size and the timings of each row (render = splat + decode per target frame).

# %%
print(A.format_table(results, ["splat", "blocks", "dim"], [
    A.Column("psnr", "PSNR"), A.Column("paper:PSNR", "paper PSNR"),
    A.Column("ssim", "SSIM", 3), A.Column("lpips", "LPIPS", 3),
    A.Column("decoder_dim", "E here"), A.Column("decoder_params", "decoder params"), A.Column("params", "params"),
    A.Column("recon_s", "recon ms", 1, 1000.0), A.Column("render_s", "render ms/frame", 1, 1000.0),
]))
