"""The tiny Long-LRM of ``../shared/golden/long_lrm_tiny``: its configuration, and its
official Gaussians as a colour-mode scene with their input cameras as render targets."""

from dataclasses import replace

import jax.numpy as jnp
import numpy as np

from llrmpp_jax import config as C
from tests.helpers.environment import shared_path


def golden_backbone_config() -> C.BackboneConfig:
    """The tiny Long-LRM of ../shared/golden/long_lrm_tiny/config.json."""
    return C.BackboneConfig(
        dims=(32, 64),
        pattern="mmt",
        num_layers=6,
        merge_layers=(3,),
        num_global_tokens=2,
        mamba=C.Mamba2Config(d_state=16, headdim=16, chunk_size=256),
        transformer=C.TransformerConfig(head_dim=16, qk_norm=False),
    )


def golden_model_config() -> C.ModelConfig:
    return C.ModelConfig(backbone=golden_backbone_config(), head=C.GaussianHeadConfig(mode="color"))


def golden_colour_scene():
    """The golden Long-LRM Gaussians (float64) and their input cameras as render targets."""
    from llrmpp_jax.gaussians import Gaussians

    out = np.load(shared_path("golden", "long_lrm_tiny", "outputs.npz"))
    g = Gaussians(
        jnp.asarray(out["xyz"]),
        jnp.asarray(out["render_quats"]),
        jnp.asarray(out["render_scales"]),
        jnp.asarray(out["render_opacities"]),
        jnp.asarray(out["feature"].reshape(2, 3072, 48)),
    )
    c2w = jnp.asarray(np.linalg.inv(out["render_viewmats"]))
    ks = out["render_Ks"]
    intr = jnp.asarray(np.stack([ks[..., 0, 0], ks[..., 1, 1], ks[..., 0, 2], ks[..., 1, 2]], -1))
    return replace(golden_model_config(), outputs=("rgb", "depth")), g, c2w, intr
