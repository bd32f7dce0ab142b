"""Conversion table for Long-LRM PyTorch ``state_dict``s (facts §5), one builder per block type.

Each builder takes ``prefix`` (a regular-expression fragment matched before the block's
own key names: escape literal dots, named groups allowed, e.g.
``r"processor\\.blocks\\.(?P<i>\\d+)\\."``) and ``target`` (the parameter-path template
placed before the block's own parameter names, e.g. ``"blocks_{i}/"``), and returns the
block's :class:`~llrmpp_jax.convert.table.Rule` list; a model's table is the concatenation.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from llrmpp_jax.convert.table import Rule, conv1d_depthwise, conv2d, convert_state_dict, identity, linear
from llrmpp_jax.errors import UserError


def mamba2_block_rules(prefix: str = "", target: str = "") -> list[Rule]:
    """Long-LRM ``Mamba2Block`` -> :func:`llrmpp_jax.nn.mamba2.mamba2_block` parameters.

    ``norm.weight`` -> ``norm/scale``; ``mamba.{in,out}_proj.weight`` (out, in) ->
    ``{in,out}_proj/kernel`` (in, out); per direction d in {0, 1},
    ``mamba.mamba_scans.d.{conv1d.weight (C,1,K), conv1d.bias, dt_bias, A_log, D, norm.weight}``
    -> ``mamba_scans_d/{conv_kernel (K,C), conv_bias, dt_bias, A_log, D, norm_scale}``.
    """
    scan = prefix + r"mamba\.mamba_scans\.(?P<scan_dir>[01])\."
    scan_target = target + "mamba_scans_{scan_dir}/"
    return [
        Rule(prefix + r"norm\.weight", target + "norm/scale", identity),
        Rule(prefix + r"mamba\.in_proj\.weight", target + "in_proj/kernel", linear),
        Rule(prefix + r"mamba\.out_proj\.weight", target + "out_proj/kernel", linear),
        Rule(scan + r"conv1d\.weight", scan_target + "conv_kernel", conv1d_depthwise),
        Rule(scan + r"conv1d\.bias", scan_target + "conv_bias", identity),
        Rule(scan + r"(?P<name>dt_bias|A_log|D)", scan_target + "{name}", identity),
        Rule(scan + r"norm\.weight", scan_target + "norm_scale", identity),
    ]


def transformer_block_rules(prefix: str = "", target: str = "") -> list[Rule]:
    """Long-LRM ``TransformerBlock`` -> :class:`llrmpp_jax.nn.transformer.TransformerBlock`.

    ``norm{1,2}.weight`` -> ``norm{1,2}/scale``; ``attn.qkv``, ``attn.proj``, ``mlp.fc1``,
    ``mlp.fc2`` weights (out, in) -> ``.../kernel`` (in, out). Long-LRM has no QK-norm, so a
    model converted from it must use ``TransformerConfig(qk_norm=False)``.
    """
    return [
        Rule(prefix + r"(?P<n>norm[12])\.weight", target + "{n}/scale", identity),
        Rule(prefix + r"(?P<m>attn|mlp)\.(?P<l>qkv|proj|fc1|fc2)\.weight", target + "{m}/{l}/kernel", linear),
    ]


def backbone_rules(prefix: str = "", target: str = "") -> list[Rule]:
    """Tokenizer, global tokens, input LayerNorm, every block and the token merges.

    Block types are not visible in the keys' regexes alone, so both block tables are
    included; a key matches exactly one of them (Mamba keys carry ``mamba.``, transformer
    keys ``attn.``/``mlp.``/``norm1``/``norm2``; the shared ``norm.weight`` is Mamba's).
    """
    blk = prefix + r"processor\.blocks\.(?P<i>\d+)\."
    return [
        Rule(prefix + r"global_token_init", target + "global_tokens", lambda w: w[0]),
        Rule(prefix + r"tokenizer\.weight", target + "tokenizer/kernel", linear),
        Rule(prefix + r"input_layernorm\.weight", target + "input_norm/scale", identity),
        *mamba2_block_rules(blk, target + "blocks_{i}/"),
        *transformer_block_rules(blk, target + "blocks_{i}/"),
        Rule(prefix + r"processor\.resize_blocks\.(?P<k>\d+)\.weight", target + "merge_{k}/resize/kernel", linear),
        Rule(prefix + r"processor\.resize_blocks\.(?P<k>\d+)\.bias", target + "merge_{k}/resize/bias", identity),
        Rule(prefix + r"processor\.merge_blocks\.(?P<k>\d+)\.weight", target + "merge_{k}/conv/kernel", conv2d),
        Rule(prefix + r"processor\.merge_blocks\.(?P<k>\d+)\.bias", target + "merge_{k}/conv/bias", identity),
    ]


def long_lrm_rules() -> list[Rule]:
    """The whole Long-LRM model -> :class:`llrmpp_jax.model.LongLRMPP` in colour mode."""
    return [
        *backbone_rules(target="backbone/"),
        Rule(r"tokenDecoder\.0\.weight", "head/norm/scale", identity),
        Rule(r"tokenDecoder\.1\.weight", "head/proj/kernel", linear),
    ]


# Training checkpoints also hold frozen loss networks (VGG, DepthAnything): not model params.
MODEL_PREFIXES = ("global_token_init", "tokenizer.", "input_layernorm.", "processor.", "tokenDecoder.")


def convert_backbone(state_dict, cfg, *, dtype=np.float32, source: str = "state_dict") -> dict:
    """Long-LRM ``state_dict`` -> :class:`~llrmpp_jax.nn.backbone.Backbone` params for ``cfg``
    (checked leaf by leaf against ``jax.eval_shape`` of the backbone's init)."""
    from llrmpp_jax.nn.backbone import Backbone

    p = 8  # shapes of the params do not depend on the image size; any valid size works
    mult = p * 2 ** len(cfg.merge_layers)
    pixels = jax.ShapeDtypeStruct((1, 1, mult, mult, 9), jnp.float32)
    expected = jax.eval_shape(Backbone(cfg, p).init, jax.random.key(0), pixels)["params"]
    return convert_state_dict(
        state_dict, backbone_rules(), expected=expected, keep_prefixes=MODEL_PREFIXES[:4], dtype=dtype, source=source
    )


def convert_long_lrm(state_dict, cfg, *, dtype=np.float32, source: str = "state_dict") -> dict:
    """Long-LRM ``state_dict`` (or a training checkpoint's ``model``) -> full model params.

    ``cfg`` must be a colour-mode :class:`~llrmpp_jax.config.ModelConfig` describing the same
    architecture (e.g. :func:`llrmpp_jax.config.long_lrm`); every parameter is checked
    against ``jax.eval_shape`` of the model's init, so a config mismatch lists each
    offending key.
    """
    from llrmpp_jax.model import init_params

    if cfg.head.mode != "color":
        raise UserError("convert_long_lrm: Long-LRM checkpoints need a colour-mode ModelConfig")
    m = cfg.size_multiple
    expected = jax.eval_shape(lambda k: init_params(k, cfg, 1, m, m), jax.random.key(0))
    return convert_state_dict(
        state_dict, long_lrm_rules(), expected=expected, keep_prefixes=MODEL_PREFIXES, dtype=dtype, source=source
    )


def unused_keys(state_dict) -> list[str]:
    """Keys of ``state_dict`` outside the model's prefixes (loss networks, EMA copies, ...)."""
    return sorted(k for k in state_dict if not k.startswith(MODEL_PREFIXES))


def convert_checkpoint(path: str, out: str, cfg, *, allow_unused: bool = False) -> tuple[int, list[str]]:
    """Long-LRM ``.pt``/``.npz`` at ``path`` -> a verified params folder at ``out`` (see
    :func:`llrmpp_jax.params_io.save_params`). Returns ``(parameter count, unused keys)``;
    unused keys are an error unless ``allow_unused``."""
    from llrmpp_jax.convert.table import load_torch_state_dict
    from llrmpp_jax.params_io import save_params

    state_dict = load_torch_state_dict(path)
    unused = unused_keys(state_dict)
    if unused and not allow_unused:
        more = " ..." if len(unused) > 5 else ""
        raise UserError(
            f"{path}: {len(unused)} key(s) outside the model's prefixes {MODEL_PREFIXES}: "
            f"{', '.join(unused[:5])}{more} (pass --allow-unused to convert anyway)"
        )
    params = convert_long_lrm(state_dict, cfg, source=path)
    return save_params(out, params, cfg), unused
