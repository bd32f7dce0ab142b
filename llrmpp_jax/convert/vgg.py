"""torchvision VGG16 / VGG19 ``state_dict`` -> the VGG parameter dict of ``perceptual.py``.

Parameters are named by VGG layer, ``{"conv3_2": {"kernel": [3, 3, Cin, Cout],
"bias": [Cout]}, ...}``, so the same forward pass serves VGG16 (LPIPS) and VGG19 (the
Long-LRM perceptual loss). Two PyTorch layouts are read:

* torchvision ``vgg16()/vgg19().state_dict()``: ``features.{idx}.weight`` (Cout, Cin, 3, 3)
  and ``features.{idx}.bias``; ``classifier.*`` is ignored;
* a Long-LRM training checkpoint: ``perceptual_loss.blocks.{k}.0.{idx}.{weight,bias}``
  (same torchvision indices, sliced into blocks; only the convolutions up to conv5_2).

A file may stop early (Long-LRM keeps conv1_1..conv5_2 of VGG19), but the convolutions it
holds must be a gap-free prefix of the architecture with the architecture's shapes.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import numpy as np

from llrmpp_jax.convert.table import Rule, conv2d, convert_state_dict

# Output channels per block and convolutions per block.
_WIDTHS = (64, 128, 256, 512, 512)
_DEPTHS = {"vgg16": (2, 2, 3, 3, 3), "vgg19": (2, 2, 4, 4, 4)}


def vgg_layers(arch: str) -> list[tuple[str, int, int, int]]:
    """``(name, torchvision feature index, Cin, Cout)`` for every 3x3 conv of ``arch``.

    ``arch`` is ``"vgg16"`` or ``"vgg19"``. torchvision's ``features`` interleaves
    conv, ReLU and (after each block) max-pool modules, so conv indices skip the ReLUs
    and pools: VGG19 -> 0, 2, 5, 7, 10, 12, 14, 16, 19, ...
    """
    if arch not in _DEPTHS:
        raise ValueError(f"arch={arch!r}, expected one of {sorted(_DEPTHS)}")
    layers, idx, cin = [], 0, 3
    for block, (width, depth) in enumerate(zip(_WIDTHS, _DEPTHS[arch]), start=1):
        for i in range(1, depth + 1):
            layers.append((f"conv{block}_{i}", idx, cin, width))
            idx += 2  # conv + ReLU
            cin = width
        idx += 1  # pooling
    return layers


def vgg_rules(arch: str) -> list[Rule]:
    """Conversion table for ``arch``: torchvision and Long-LRM key layouts, both transposed to HWIO."""
    rules = []
    for name, idx, _, _ in vgg_layers(arch):
        for prefix in (r"features\.", r"perceptual_loss\.blocks\.\d+\.0\."):
            rules.append(Rule(rf"{prefix}{idx}\.weight", f"{name}/kernel", conv2d))
            rules.append(Rule(rf"{prefix}{idx}\.bias", f"{name}/bias"))
    return rules


def convert_vgg(
    state_dict: Mapping[str, Any], arch: str = "vgg19", *, source: str = "state_dict"
) -> dict[str, dict[str, np.ndarray]]:
    """Convert a torchvision-layout (or Long-LRM checkpoint) VGG ``state_dict``.

    Args:
      state_dict: torch key -> array; keys outside ``features.`` and
        ``perceptual_loss.blocks.`` (classifier, the rest of a model) are dropped.
      arch: ``"vgg16"`` or ``"vgg19"``.
      source: name used in error messages.

    Returns:
      ``{conv_name: {"kernel": float32 [3, 3, Cin, Cout], "bias": float32 [Cout]}}``.

    Raises:
      ValueError: no VGG key at all, a key without a rule, a missing conv before the
        last one present, or a shape that is not ``arch``'s.
    """
    layers = vgg_layers(arch)
    prefixes = ("features.", "perceptual_loss.blocks.")
    n_weights = sum(1 for k in state_dict if k.startswith(prefixes) and k.endswith(".weight"))
    if n_weights == 0:
        raise ValueError(
            f"{source}: no VGG convolution weights (keys 'features.{{idx}}.weight' or "
            f"'perceptual_loss.blocks.{{k}}.0.{{idx}}.weight'); got keys {sorted(state_dict)[:8]}..."
        )
    if n_weights > len(layers):
        raise ValueError(
            f"{source}: {n_weights} convolution weights, but {arch} has only {len(layers)}"
        )
    # Zero-stride views: only ``.shape`` is read, nothing is allocated.
    expected = {
        name: {
            "kernel": np.broadcast_to(np.float32(0), (3, 3, cin, cout)),
            "bias": np.broadcast_to(np.float32(0), (cout,)),
        }
        for name, _, cin, cout in layers[:n_weights]
    }
    return convert_state_dict(
        state_dict, vgg_rules(arch), expected=expected, keep_prefixes=prefixes, source=source
    )
