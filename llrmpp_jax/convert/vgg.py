"""torchvision VGG16 / VGG19 ``state_dict`` -> the VGG parameter dict of ``perceptual.py``.

Parameters are named by VGG layer, ``{"conv3_2": {"kernel": [3, 3, Cin, Cout],
"bias": [Cout]}, ...}``, so the same forward pass serves VGG16 (LPIPS) and VGG19 (the
Long-LRM perceptual loss). Two PyTorch layouts are read:

* torchvision ``vgg16()/vgg19().state_dict()``: ``features.{idx}.weight`` (Cout, Cin, 3, 3)
  and ``features.{idx}.bias``; ``classifier.*`` is ignored;
* a Long-LRM training checkpoint: ``perceptual_loss.blocks.{k}.0.{idx}.{weight,bias}``
  (same torchvision indices, sliced into blocks; only the convolutions up to conv5_2).

A file may stop early (Long-LRM keeps conv1_1..conv5_2 of VGG19), but the convolutions it
holds must be a gap-free prefix of the architecture with the architecture's shapes; a file
of another architecture (e.g. VGG16 given as VGG19) is rejected with one line naming the
first key, in torchvision order, where it departs from ``arch``.
"""

from __future__ import annotations

import re
from collections.abc import Mapping
from typing import Any

import numpy as np

from llrmpp_jax.convert.table import Rule, conv2d, convert_state_dict
from llrmpp_jax.errors import UserError

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
        raise UserError(f"arch={arch!r}, expected one of {sorted(_DEPTHS)}")
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


_KEY = re.compile(r"(?P<prefix>features\.|perceptual_loss\.blocks\.\d+\.0\.)(?P<idx>\d+)\.(?P<kind>weight|bias)")


def first_mismatch(state_dict: Mapping[str, Any], arch: str) -> str | None:
    """``"'key': why"`` for the first VGG key (torchvision index order, weight before bias)
    that departs from ``arch``: a tensor at an index where ``arch`` has no convolution, a
    wrong shape, or a convolution missing before the file's last one. None if it matches."""
    convs = {idx: (name, cin, cout) for name, idx, cin, cout in vgg_layers(arch)}
    found = {}
    for key in state_dict:
        m = _KEY.fullmatch(key)
        if m is not None:
            found[(int(m.group("idx")), m.group("kind") == "bias")] = (key, m.group("prefix"))
    if not found:
        return None
    prefix = next(iter(found.values()))[1]
    last = max(idx for idx, _ in found)
    for idx, is_bias in sorted(set(found) | {(i, b) for i in convs if i <= last for b in (False, True)}):
        kind = "bias" if is_bias else "weight"
        if (idx, is_bias) not in found:
            return f"'{prefix}{idx}.{kind}': missing ({arch} has {convs[idx][0]} there)"
        key = found[(idx, is_bias)][0]
        if idx not in convs:
            return f"'{key}': {arch} has no convolution at index {idx}"
        name, cin, cout = convs[idx]
        want = (cout,) if is_bias else (cout, cin, 3, 3)
        got = tuple(np.shape(state_dict[key]))
        if got != want:
            flax = f"{name}/bias {want}" if is_bias else f"{name}/kernel (3, 3, {cin}, {cout})"
            return f"'{key}': {arch}'s {flax} needs torch shape {want}, got {got}"
    return None


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
        raise UserError(
            f"{source}: no VGG convolution weights (keys 'features.{{idx}}.weight' or "
            f"'perceptual_loss.blocks.{{k}}.0.{{idx}}.weight'); got keys {sorted(state_dict)[:8]}..."
        )
    mismatch = first_mismatch(state_dict, arch)
    if mismatch is not None:
        raise UserError(f"{source}: not a {arch} state_dict; first mismatching key {mismatch}")
    # Zero-stride views: only ``.shape`` is read, nothing is allocated.
    expected = {
        name: {
            "kernel": np.broadcast_to(np.float32(0), (3, 3, cin, cout)),
            "bias": np.broadcast_to(np.float32(0), (cout,)),
        }
        for name, _, cin, cout in layers[:n_weights]
    }
    return convert_state_dict(state_dict, vgg_rules(arch), expected=expected, keep_prefixes=prefixes, source=source)
