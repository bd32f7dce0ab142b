"""Patchify / unpatchify: images <-> token sequences (reference facts §1.2).

Same layout as Long-LRM's ``rearrange("b v (hh ph ww pw) d -> b (v hh ww) (ph pw d)")``:
tokens are view-major, then row-major over the patch grid; the features inside a
token are ordered ``(ph, pw, c)`` with the channel fastest. Keeping this order exactly
is what lets a PyTorch ``tokenizer.weight`` (in = p*p*C) be used unchanged.
"""

from __future__ import annotations

import jax.numpy as jnp

from llrmpp_jax.array_typing import Array, ArrayLike, Float


def patchify(x: Float[ArrayLike, "... V H W C"], p: int) -> Float[Array, "... L pC"]:
    """Cut ``[..., V, H, W, C]`` images into non-overlapping ``p x p`` patches.

    Returns ``[..., V*h*w, p*p*C]`` with ``h = H/p``, ``w = W/p``; token
    ``(v*h + i)*w + j`` holds patch row ``i``, column ``j`` of view ``v``, its features
    ordered ``(ph, pw, c)``.

    Raises:
      ValueError: ``p < 1``, fewer than 4 axes, or H / W not a multiple of ``p``.
    """
    if p < 1:
        raise ValueError(f"patchify: patch size p must be >= 1, got {p}")
    if x.ndim < 4:
        raise ValueError(f"patchify: x must be [..., V, H, W, C], got shape {x.shape}")
    *lead, v, hh, ww, c = x.shape
    if hh % p or ww % p:
        raise ValueError(f"patchify: image size H={hh}, W={ww} (x shape {x.shape}) must be multiples of p={p}")
    h, w = hh // p, ww // p
    n = len(lead)
    x = x.reshape(*lead, v, h, p, w, p, c)
    # [..., v, h, ph, w, pw, c] -> [..., v, h, w, ph, pw, c]
    perm = (*range(n), n, n + 1, n + 3, n + 2, n + 4, n + 5)
    return jnp.transpose(x, perm).reshape(*lead, v * h * w, p * p * c)


def unpatchify(tokens: Float[ArrayLike, "... L pC"], p: int, v: int, h: int, w: int) -> Float[Array, "... V H W C"]:
    """Exact inverse of :func:`patchify`: ``[..., V*h*w, p*p*C] -> [..., V, h*p, w*p, C]``.

    ``h, w`` is the token grid per view; ``C`` is inferred from the last axis.

    Raises:
      ValueError: the token count is not ``v*h*w`` or the last axis is not a multiple of ``p*p``.
    """
    if p < 1 or v < 1 or h < 1 or w < 1:
        raise ValueError(f"unpatchify: p, v, h, w must be >= 1, got p={p}, v={v}, h={h}, w={w}")
    if tokens.ndim < 2:
        raise ValueError(f"unpatchify: tokens must be [..., L, p*p*C], got shape {tokens.shape}")
    *lead, length, feat = tokens.shape
    if length != v * h * w:
        raise ValueError(
            f"unpatchify: tokens shape {tokens.shape} has L={length} tokens, expected v*h*w = {v}*{h}*{w} = {v * h * w}"
        )
    if feat % (p * p):
        raise ValueError(
            f"unpatchify: tokens shape {tokens.shape} has {feat} features per token, not a multiple of p*p = {p * p}"
        )
    c = feat // (p * p)
    n = len(lead)
    x = tokens.reshape(*lead, v, h, w, p, p, c)
    # [..., v, h, w, ph, pw, c] -> [..., v, h, ph, w, pw, c]
    perm = (*range(n), n, n + 1, n + 3, n + 2, n + 4, n + 5)
    return jnp.transpose(x, perm).reshape(*lead, v, h * p, w * p, c)
