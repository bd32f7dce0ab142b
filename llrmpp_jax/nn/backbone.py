"""The input-processing backbone: tokenizer, global tokens, a Mamba2/transformer stack.

Long-LRM++ (paper §3.1): patchify (p=8) -> bias-free linear to D -> two learned global
tokens prepended -> bias-free LayerNorm -> 24 blocks ``{1T7M}x3``. Long-LRM (the
predecessor) additionally merges tokens once (before block 8) with a grouped 2x2
stride-2 convolution on the image tokens and a linear on the global tokens; that path
is kept so official Long-LRM checkpoints convert and run.

Token order is view-major, then row-major over patches, global tokens first (the
bidirectional Mamba2 scans this order forwards and backwards).
"""

from __future__ import annotations

import math
import re
from typing import NamedTuple

import flax.linen as nn
import jax
import jax.numpy as jnp

from llrmpp_jax.array_typing import Array, Float
from llrmpp_jax.config import BackboneConfig
from llrmpp_jax.nn.mamba2 import Mamba2Block
from llrmpp_jax.nn.norms import LayerNorm
from llrmpp_jax.nn.patchify import patchify
from llrmpp_jax.nn.remat_loops import remat_blocks
from llrmpp_jax.nn.transformer import TransformerBlock

_GROUP = re.compile(r"\{([^{}]*)\}x(\d+)")
_RUN = re.compile(r"(\d*)([A-Za-z])")


def parse_block_pattern(pattern: str, allowed: str, num_layers: int | None = None) -> str:
    """Expand a block pattern into one upper-case letter per block.

    ``"{1T7M}x3"`` -> ``"TMMMMMMM" * 3``; ``"2L3G"`` -> ``"LLGGG"``; a plain string such
    as Long-LRM's ``"mmmmmmmt"`` is upper-cased and, when ``num_layers`` is given and the
    expansion is shorter, tiled to that length (Long-LRM's rule). ``allowed`` lists the
    legal letters, e.g. ``"TM"``.
    """
    expanded = _GROUP.sub(lambda m: m.group(1) * int(m.group(2)), pattern.replace(" ", ""))
    out, pos = [], 0
    for m in _RUN.finditer(expanded):
        if m.start() != pos:
            break
        out.append(m.group(2).upper() * (int(m.group(1)) if m.group(1) else 1))
        pos = m.end()
    layout = "".join(out)
    if pos != len(expanded) or not layout:
        raise ValueError(f"block pattern {pattern!r}: cannot parse near {expanded[pos:]!r}")
    bad = sorted(set(layout) - set(allowed.upper()))
    if bad:
        raise ValueError(f"block pattern {pattern!r}: letters {bad} not in {allowed!r}")
    if num_layers is not None:
        if len(layout) > num_layers:
            raise ValueError(f"block pattern {pattern!r} expands to {len(layout)} blocks > num_layers={num_layers}")
        layout = (layout * (num_layers // len(layout) + 1))[:num_layers]
    return layout


class TokenMerge(nn.Module):
    """Long-LRM token merge: 2x2 stride-2 grouped conv (groups = d_in) + linear for globals.

    Output channel ``o`` reads input channel ``o // (d_out // d_in)``, as PyTorch's
    ``Conv2d(groups=d_in)``; parameter layout matches the converter's ``conv2d`` rule.
    """

    d_in: int
    d_out: int

    @nn.compact
    def __call__(
        self,
        global_tokens: Float[Array, "B G Din"],
        tokens: Float[Array, "B L Din"],
        views: int,
        grid: tuple[int, int],
    ) -> tuple[Float[Array, "B G Dout"], Float[Array, "B Lm Dout"], tuple[int, int]]:
        h, w = grid
        if h % 2 or w % 2:
            raise ValueError(f"TokenMerge: token grid {grid} must have even sides")
        b = tokens.shape[0]
        g = nn.Dense(self.d_out, name="resize")(global_tokens)
        img = tokens.reshape(b * views, h, w, self.d_in)
        img = nn.Conv(
            self.d_out,
            (2, 2),
            strides=(2, 2),
            padding="VALID",
            feature_group_count=self.d_in,
            name="conv",
        )(img)
        return g, img.reshape(b, views * (h // 2) * (w // 2), self.d_out), (h // 2, w // 2)


class BackboneOutput(NamedTuple):
    global_tokens: Float[Array, "B G D"]
    tokens: Float[Array, "B L D"]  # L = V*h*w, view-major then row-major
    grid: tuple[int, int]  # (h, w) of the final token grid per view


class Backbone(nn.Module):
    """Tokenizer + global tokens + block stack.

    ``__call__(pixels)`` takes per-pixel input features ``[B, V, H, W, C]`` (C=9 for
    ``[rgb*2-1, o x d, d]``) with H, W multiples of ``patch_size`` (times 2 per merge).

    With ``cfg.remat`` every block is rematerialised and, outside ``init``, each stage's
    blocks run as loops (:func:`remat_blocks`) over the blocks' own ``blocks_<i>``
    parameters: same numbers, same parameter tree, but a backward pass that holds one
    repetition of the pattern at a time. ``init`` creates the blocks one by one (the same
    initial values with and without remat).
    """

    cfg: BackboneConfig
    patch_size: int

    def layout(self) -> str:
        return parse_block_pattern(self.cfg.pattern, "TM", self.cfg.num_layers)

    def _block(self, kind: str, dim: int, name: str | None, remat: bool = False, **kw) -> nn.Module:
        """Block ``kind`` (``"M"``/``"T"``) of width ``dim``; ``kw`` goes to the constructor
        (``parent=None``: an unbound module to ``apply`` with given parameters)."""
        if kind == "M":
            return (nn.remat(Mamba2Block) if remat else Mamba2Block)(d_model=dim, cfg=self.cfg.mamba, name=name, **kw)
        cls = nn.remat(TransformerBlock) if remat else TransformerBlock
        return cls(dim=dim, cfg=self.cfg.transformer, attention="global", name=name, **kw)

    @nn.compact
    def __call__(self, pixels: Float[Array, "B V H W C"]) -> BackboneOutput:
        cfg, p = self.cfg, self.patch_size
        if pixels.ndim != 5:
            raise ValueError(f"Backbone: pixels must be [B, V, H, W, C], got shape {pixels.shape}")
        b, v, hh, ww, _ = pixels.shape
        mult = p * 2 ** len(cfg.merge_layers)
        if hh % mult or ww % mult:
            raise ValueError(
                f"Backbone: image size {hh}x{ww} must be a multiple of {mult} "
                f"(patch {p} x 2^{len(cfg.merge_layers)} merges)"
            )
        grid = (hh // p, ww // p)
        g = self.param(
            "global_tokens",
            nn.initializers.truncated_normal(0.02),
            (cfg.num_global_tokens, cfg.dims[0]),
            jnp.float32,
        )
        # The tokens take the parameters' dtype: bf16 when the train step casts them to its
        # compute dtype. The pixel features arrive float32 and would otherwise promote the
        # whole stack to float32 (twice the activation memory; bench_train.json paper_stage4).
        x = nn.Dense(cfg.dims[0], use_bias=False, name="tokenizer")(patchify(pixels, p).astype(g.dtype))
        x = jnp.concatenate([jnp.broadcast_to(g[None], (b, *g.shape)), x], axis=1)
        x = LayerNorm(name="input_norm")(x)

        ng, layout = cfg.num_global_tokens, self.layout()
        bounds = [0, *sorted(cfg.merge_layers), len(layout)]
        for stage, (start, stop) in enumerate(zip(bounds[:-1], bounds[1:])):  # one stage per width
            if stage:
                gt, it, grid = TokenMerge(cfg.dims[stage - 1], cfg.dims[stage], name=f"merge_{stage - 1}")(
                    x[:, :ng], x[:, ng:], v, grid
                )
                x = jnp.concatenate([gt, it], axis=1)
            kinds, d = layout[start:stop], cfg.dims[stage]
            if cfg.remat and not self.is_initializing():
                params = [self.variables["params"][f"blocks_{i}"] for i in range(start, stop)]
                # remat_blocks calls the lambda before the loop moves on.
                x = remat_blocks(kinds, lambda kind: self._block(kind, d, None, parent=None), params, x)  # noqa: B023
            else:
                for i, kind in enumerate(kinds, start):
                    x = self._block(kind, d, f"blocks_{i}", remat=cfg.remat)(x)
        return BackboneOutput(x[:, :ng], x[:, ng:], grid)


def count_params(params) -> int:
    """Number of scalars in a parameter pytree (works on ``jax.eval_shape`` output)."""
    return sum(math.prod(leaf.shape) for leaf in jax.tree.leaves(params))
