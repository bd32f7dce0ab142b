"""Conversion table for Long-LRM PyTorch ``state_dict``s (facts §5), one builder per block type.

Each builder takes ``prefix`` (a regular-expression fragment matched before the block's
own key names: escape literal dots, named groups allowed, e.g.
``r"processor\\.blocks\\.(?P<i>\\d+)\\."``) and ``target`` (the parameter-path template
placed before the block's own parameter names, e.g. ``"blocks_{i}/"``), and returns the
block's :class:`~llrmpp_jax.convert.table.Rule` list; a model's table is the concatenation.
"""

from __future__ import annotations

from llrmpp_jax.convert.table import Rule, conv1d_depthwise, identity, linear


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
