"""Pre-LN transformer block (Long-LRM ``model/transformer.py``, facts §1.5).

``x = x + attn(LN1(x)); x = x + mlp(LN2(x))`` with LayerNorm without bias (eps 1e-5),
an MLP of ratio 4 with exact (erf) GELU and no biases anywhere. The attention is either
global (backbone, decoder ``G``) or local k-NN (decoder ``L``), with optional QK-norm.
Submodule names mirror the PyTorch ones (``norm1``, ``attn.qkv``, ``attn.proj``,
``norm2``, ``mlp.fc1``, ``mlp.fc2``) so a state_dict converts key by key.
"""

from __future__ import annotations

from typing import Literal

import flax.linen as nn

from llrmpp_jax.array_typing import Array, ArrayLike, DTypeLike, Float
from llrmpp_jax.config import TransformerConfig
from llrmpp_jax.nn.attention import Attention
from llrmpp_jax.nn.initializers import DENSE_INIT
from llrmpp_jax.nn.local_attention import LocalAttention
from llrmpp_jax.nn.norms import LayerNorm


class Mlp(nn.Module):
    """``fc2(GELU_exact(fc1(x)))`` without biases: ``[..., D] -> [..., D]`` via ``hidden``."""

    dim: int
    hidden: int
    dtype: DTypeLike | None = None

    @nn.compact
    def __call__(self, x: Float[Array, "... D"]) -> Float[Array, "... D"]:
        y = nn.Dense(self.hidden, use_bias=False, kernel_init=DENSE_INIT, dtype=self.dtype, name="fc1")(x)
        y = nn.gelu(y, approximate=False)
        return nn.Dense(self.dim, use_bias=False, kernel_init=DENSE_INIT, dtype=self.dtype, name="fc2")(y)


class TransformerBlock(nn.Module):
    """Pre-LN transformer block: ``[..., L, D] -> [..., L, D]``.

    ``attention="global"`` attends over all L tokens; ``attention="local"`` needs
    ``grid=(h, w)`` with ``L = h*w`` (row-major) and attends to ``num_neighbours``
    nearest grid tokens (:class:`LocalAttention`). ``cfg.attention_impl`` selects the
    global-attention kernel (``"blockwise"``, ``"xla"``, ``"cudnn"`` on GPU, in bf16, or ``"splash"`` on TPU).
    ``dtype`` is the compute dtype of the Dense layers (None: from input and params);
    the residual stream keeps the dtype of ``x``.

    Params: ``norm1/scale``, ``attn/...`` (see :class:`Attention` / :class:`LocalAttention`),
    ``norm2/scale``, ``mlp/fc1/kernel [D, 4D]``, ``mlp/fc2/kernel [4D, D]``.
    """

    dim: int
    cfg: TransformerConfig
    attention: Literal["global", "local"] = "global"
    grid: tuple[int, int] | None = None
    num_neighbours: int = 64
    dtype: DTypeLike | None = None

    @nn.compact
    def __call__(self, x: Float[ArrayLike, "... L D"]) -> Float[Array, "... L D"]:
        cfg = self.cfg
        if self.attention == "global":
            attn = Attention(
                self.dim,
                cfg.head_dim,
                cfg.qk_norm,
                cfg.norm_eps,
                cfg.attention_impl,
                self.dtype,
                block_sizes=(cfg.attention_block_q, cfg.attention_block_k),
                name="attn",
            )
        elif self.attention == "local":
            if self.grid is None:
                raise ValueError("TransformerBlock: attention='local' needs grid=(h, w)")
            attn = LocalAttention(
                self.dim,
                cfg.head_dim,
                cfg.qk_norm,
                tuple(self.grid),  # pyright: ignore[reportArgumentType] -- the grid is two ints
                self.num_neighbours,
                norm_eps=cfg.norm_eps,
                dtype=self.dtype,
                name="attn",
            )
        else:
            raise ValueError(f"TransformerBlock: attention must be 'global' or 'local', got {self.attention!r}")
        x = x + attn(LayerNorm(cfg.norm_eps, name="norm1")(x)).astype(x.dtype)
        mlp = Mlp(self.dim, cfg.mlp_ratio * self.dim, self.dtype, name="mlp")
        return x + mlp(LayerNorm(cfg.norm_eps, name="norm2")(x)).astype(x.dtype)  # pyright: ignore[reportReturnType] -- jnp operations give a jax.Array; the ArrayLike input type carries through
