"""Multi-space partition, target-frame decoder and merge (paper §3.3).

For one target camera and the S partition copies of the Gaussians:

1. partition: ``softmax(Linear(f))`` gives S weights per Gaussian; copy s has opacity
   ``o * w_s`` (S=1 is exactly "no partition": the weight is 1).
2. each copy is splatted to a feature canvas ``[H/r, W/r, F]`` and the target's Plücker
   rays ``[o x d, d]`` (through the canvas pixel centres) are concatenated -> F+6.
3. decode each copy independently with the same decoder: patchify with patch ``q/r`` so
   tokens are ``(H/q, W/q)``, linear to E (plus, with ``absolute_positions``, a fixed
   2-D sin-cos embedding of the token coordinates, ``nn/position_embedding.py``), blocks
   (``L`` local k-NN attention with relative-position bias, ``G`` global), QK-norm
   everywhere, final bias-free LayerNorm.
4. merge: ``Linear(E -> 1)`` on each decoded copy gives S logits per token, softmax over
   S, weighted sum of the S token maps, then the output linear to ``q*q*C`` values per
   token, unpatchified to ``[H, W, C]``.

Output heads (our choice, documented): RGB = ``sigmoid`` (as LVSM's decoder), depth =
``exp(head + depth_bias)``, a log-depth head (positive, and the depth loss works on log
depth) offset by the config's ``depth_bias`` (``DecoderConfig``: where depths start).
"""

from __future__ import annotations

import flax.linen as nn
import jax
import jax.numpy as jnp

from llrmpp_jax.array_typing import Array, Float
from llrmpp_jax.config import DecoderConfig
from llrmpp_jax.nn.backbone import parse_block_pattern
from llrmpp_jax.nn.initializers import linear_init
from llrmpp_jax.nn.norms import LayerNorm
from llrmpp_jax.nn.patchify import patchify, unpatchify
from llrmpp_jax.nn.position_embedding import sincos_2d
from llrmpp_jax.nn.remat_loops import remat_blocks
from llrmpp_jax.nn.transformer import TransformerBlock

OUTPUT_CHANNELS = {"rgb": 3, "depth": 1}


def partition_opacities(opacities: Float[Array, " N"], logits: Float[Array, "N S"]) -> Float[Array, "S N"]:
    """Opacity of each of the S copies: ``o * softmax(logits)_s``."""
    return jax.nn.softmax(logits, axis=-1).T * opacities[None, :]


class TargetDecoder(nn.Module):
    """Canvases of the S copies -> merged output image for one batch of targets.

    ``__call__(canvas, outputs)`` takes ``[M, S, H/r, W/r, F+6]`` (M = batch x targets) and
    returns ``{output: [M, H, W, C]}`` with C = 3 for ``"rgb"`` and 1 for ``"depth"``. The
    blocks and the merge are shared (computed once); each output has its own linear head
    (``head_rgb``, ``head_depth``).
    """

    cfg: DecoderConfig

    @nn.compact
    def __call__(
        self, canvas: Float[Array, "M S Hc Wc C"], outputs: tuple[str, ...] = ("rgb",)
    ) -> dict[str, Float[Array, "M H W Co"]]:
        cfg = self.cfg
        bad = [o for o in outputs if o not in OUTPUT_CHANNELS]
        if bad or not outputs:
            raise ValueError(f"TargetDecoder: outputs must be among {sorted(OUTPUT_CHANNELS)}, got {outputs!r}")
        m, s, hc, wc, _ = canvas.shape
        cp = cfg.token_stride // cfg.canvas_ratio  # canvas pixels per token side
        if hc % cp or wc % cp:
            raise ValueError(f"TargetDecoder: canvas {hc}x{wc} is not a multiple of the token patch {cp}")
        grid = (hc // cp, wc // cp)
        x = patchify(canvas.reshape(m * s, 1, hc, wc, -1), cp)  # [M*S, L, cp*cp*C]
        x = nn.Dense(cfg.dim, use_bias=False, name="tokenizer", kernel_init=linear_init(cfg.init_std))(x)
        if cfg.absolute_positions:
            x = x + jnp.asarray(sincos_2d(*grid, cfg.dim), x.dtype)[None]

        def block(kind: str, name: str | None, remat: bool = False, **kw) -> nn.Module:
            cls = nn.remat(TransformerBlock) if remat else TransformerBlock
            return cls(
                dim=cfg.dim,
                cfg=cfg.transformer,
                attention="local" if kind == "L" else "global",
                grid=grid,
                num_neighbours=cfg.num_neighbours,
                name=name,
                **kw,
            )

        kinds = parse_block_pattern(cfg.blocks, "LG")
        if cfg.remat and not self.is_initializing():  # loops whose backward holds one block
            params = [self.variables["params"][f"blocks_{i}"] for i in range(len(kinds))]
            x = remat_blocks(kinds, lambda kind: block(kind, None, parent=None), params, x)
        else:
            for i, kind in enumerate(kinds):
                x = block(kind, f"blocks_{i}", cfg.remat)(x)
        x = LayerNorm(name="norm")(x)
        x = x.reshape(m, s, grid[0] * grid[1], cfg.dim)
        merge = nn.Dense(1, use_bias=False, name="merge", kernel_init=linear_init(cfg.init_std))(x)
        x = jnp.sum(jax.nn.softmax(merge, axis=1) * x, axis=1)  # [M, L, E]
        q = cfg.token_stride
        images = {}
        for output in outputs:
            out = nn.Dense(
                q * q * OUTPUT_CHANNELS[output],
                use_bias=False,
                name=f"head_{output}",
                kernel_init=linear_init(cfg.init_std),
            )(x)
            img = unpatchify(out, q, 1, grid[0], grid[1])[:, 0]  # [M, H, W, C]
            images[output] = jax.nn.sigmoid(img) if output == "rgb" else jnp.exp(img + cfg.depth_bias)
        return images
