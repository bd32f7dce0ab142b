"""Long-LRM's bidirectional Mamba2 block (reference facts §1.4), as pure functions.

``out = x + out_proj(scan_0(zxbcdt) + flip(scan_1(flip(zxbcdt))))`` with
``zxbcdt = in_proj(rms_norm(x))``: one shared in/out projection, two scan directions with
their own conv, ``dt_bias``, ``A_log``, ``D`` and gated norm. Each direction
(:func:`mamba2_scan_direction`) is ``mamba_split_conv1d_scan_combined`` without the
out-projection: split ``[z | x | B | C | dt]``, causal depthwise conv (k=4) + SiLU on
``x|B|C``, ``dt = softplus(dt + dt_bias)``, ``A = -exp(A_log)``, the SSD scan with the
``D`` skip, then ``rms_norm(y * silu(z)) * w`` over the whole d_inner.

The split is done on the weights, not on the activations: ``in_proj``'s kernel is cut
into its five column blocks (:class:`InProj`) and the per-channel conv into its ``x|B|C``
channels, so no ``[..., L, E]`` activation is sliced. The backward pass of an activation
slice is a zero-padded full-size buffer; at the paper's L = 261,122 tokens those pads
were gigabytes per block.

Parameter tree (names mirror the PyTorch ``state_dict``; see ``convert/long_lrm.py``)::

    norm/scale [D]                 in_proj/kernel [D, 2*d_inner + 2*g*n + nh]
    mamba_scans_{0,1}/conv_kernel [K, d_inner + 2*g*n]   conv_bias [d_inner + 2*g*n]
                      dt_bias [nh]  A_log [nh]  D [nh]  norm_scale [d_inner]
    out_proj/kernel [d_inner, D]

Activations keep the input dtype; matmuls, norms and the scan accumulate in float32.
"""

from __future__ import annotations

import itertools
import math
from typing import NamedTuple

import flax.linen as nn
import jax
import jax.numpy as jnp

from llrmpp_jax.array_typing import Array, ArrayLike, Float, KeyArray
from llrmpp_jax.config import Mamba2Config
from llrmpp_jax.nn.norms import rms_norm
from llrmpp_jax.nn.remat_loops import remat_after_cotangent
from llrmpp_jax.nn.ssd import ssd_scan

Params = dict[str, dict[str, ArrayLike]]

# Long-LRM's Mamba2Block constants (facts §1.4 "Init").
_A_INIT_RANGE = (1.0, 16.0)
_DT_MIN, _DT_MAX, _DT_INIT_FLOOR = 1e-3, 1e-1, 1e-4


def _acc(dtype: jnp.dtype) -> jnp.dtype:
    """Accumulation dtype: float64 for float64 activations (oracles), float32 otherwise."""
    return jnp.dtype(jnp.float64) if dtype == jnp.float64 else jnp.dtype(jnp.float32)


def _dense(x: Float[Array, "... Ci"], kernel: Float[ArrayLike, "Ci Co"]) -> Float[Array, "... Co"]:
    """Bias-free linear layer, float32 (or float64) accumulation, result in the dtype of ``x``."""
    return jnp.matmul(x, kernel.astype(x.dtype), preferred_element_type=_acc(x.dtype)).astype(x.dtype)


def causal_depthwise_conv1d(
    x: Float[Array, "... L C"], kernel: Float[Array, "kw C"], bias: Float[Array, " C"]
) -> Float[Array, "... L C"]:
    """Per-channel causal convolution along L: ``y_t = b + sum_k kernel[k] * x_{t-(kw-1)+k}``.

    Zero history before t=0; tap ``kw-1`` multiplies the current token (PyTorch
    ``Conv1d(groups=C, padding=kw-1)`` truncated to the first L outputs, cross-correlation).
    One grouped ``conv_general_dilated`` (``feature_group_count=C``, kw-1 zeros on the left)
    rather than kw shifted slices: the slices' transposes in the backward are kw zero-padded
    ``[..., L+kw-1, C]`` buffers, the conv's backward is one conv of the cotangent.
    """
    if kernel.ndim != 2 or kernel.shape[1] != x.shape[-1] or bias.shape != (x.shape[-1],):
        raise ValueError(
            f"causal_depthwise_conv1d: x {x.shape} needs kernel [kw, {x.shape[-1]}] and bias "
            f"[{x.shape[-1]}], got kernel {kernel.shape} and bias {bias.shape}"
        )
    (kw, C), L = kernel.shape, x.shape[-2]
    acc = _acc(x.dtype)
    y = jax.lax.conv_general_dilated(
        x.astype(acc).reshape(-1, L, C),
        kernel.astype(acc)[:, None, :],  # [kw, 1, C]: one input channel per group
        window_strides=(1,),
        padding=[(kw - 1, 0)],
        dimension_numbers=("NWC", "WIO", "NWC"),
        feature_group_count=C,
        precision=jax.lax.Precision.HIGHEST,  # no TF32/bf16 passes: exact float32 taps
    )
    return (y + bias.astype(acc)[None, None]).reshape(x.shape).astype(x.dtype)


def gated_rms_norm(
    y: Float[Array, "... C"], z: Float[Array, "... C"], scale: Float[ArrayLike, " C"], eps: float = 1e-5
) -> Float[Array, "... C"]:
    """``rms_norm(y * silu(z)) * scale`` (mamba_ssm ``RMSNormGated``, norm after the gate)."""
    acc = _acc(y.dtype)
    gated = y.astype(acc) * jax.nn.silu(z.astype(acc))
    return rms_norm(gated, scale, eps).astype(y.dtype)


def _sizes(d_model: int, cfg: Mamba2Config) -> tuple[int, int, int, int]:
    """(d_inner, nheads, conv channels, in_proj width) for a block of width ``d_model``."""
    d_inner = cfg.d_inner(d_model)
    nheads = cfg.nheads(d_model)
    conv_ch = d_inner + 2 * cfg.ngroups * cfg.d_state
    return d_inner, nheads, conv_ch, d_inner + conv_ch + nheads


class InProj(NamedTuple):
    """``in_proj``'s output as its five column blocks ``[z | x | B | C | dt]``."""

    z: Float[Array, "... L di"]
    x: Float[Array, "... L di"]
    B: Float[Array, "... L gn"]  # gn = ngroups * d_state
    C: Float[Array, "... L gn"]
    dt: Float[Array, "... L nh"]


def in_proj_widths(d_inner: int, cfg: Mamba2Config) -> tuple[int, int, int, int, int]:
    """Widths of :class:`InProj`'s fields (in_proj's column blocks) for ``d_inner``."""
    gn = cfg.ngroups * cfg.d_state
    return d_inner, d_inner, gn, gn, d_inner // cfg.headdim


def _split_columns(a: Float[ArrayLike, "... C"], widths: tuple[int, ...]) -> list[Float[Array, "... _"]]:
    """``a`` cut along its last axis into consecutive blocks of ``widths``."""
    return jnp.split(a, list(itertools.accumulate(widths))[:-1], axis=-1)


def mamba2_scan_direction(proj: InProj, params: dict[str, ArrayLike], cfg: Mamba2Config) -> Float[Array, "... L di"]:
    """One scan direction (``Mamba2SingleScan``): in_proj's output blocks -> ``[..., L, d_inner]``.

    ``params`` holds ``conv_kernel, conv_bias, dt_bias, A_log, D, norm_scale``; the widths
    of ``proj`` are :func:`in_proj_widths` with d_inner = ``norm_scale.shape[0]``.
    """
    d_inner = params["norm_scale"].shape[0]
    g, n = cfg.ngroups, cfg.d_state
    nh = d_inner // cfg.headdim
    want = in_proj_widths(d_inner, cfg)
    got = tuple(a.shape[-1] for a in proj)
    lead_shapes = {a.shape[:-1] for a in proj}
    if got != want or len(lead_shapes) != 1 or proj.z.ndim < 2 or d_inner % cfg.headdim:
        raise ValueError(
            f"mamba2_scan_direction: in_proj blocks (z, x, B, C, dt) have shapes {[a.shape for a in proj]}, "
            f"expected [..., L, w] with widths {want} (d_inner={d_inner} a multiple of headdim={cfg.headdim}, "
            f"ngroups={g}, d_state={n}, nheads={nh})"
        )
    *lead, L, _ = proj.z.shape
    xbc_widths = want[1:4]
    kernels = _split_columns(params["conv_kernel"], xbc_widths)
    biases = _split_columns(params["conv_bias"], xbc_widths)
    x, B, C = (
        jax.nn.silu(causal_depthwise_conv1d(a, k, b)) for a, k, b in zip((proj.x, proj.B, proj.C), kernels, biases)
    )
    lead1 = (1,) * (proj.dt.ndim - 1)
    acc = _acc(proj.dt.dtype)
    dt = jax.nn.softplus(proj.dt.astype(acc) + params["dt_bias"].astype(acc).reshape(*lead1, nh))
    A = -jnp.exp(params["A_log"].astype(acc))
    y = ssd_scan(
        x.reshape(*lead, L, nh, cfg.headdim),
        dt,
        A,
        B.reshape(*lead, L, g, n),
        C.reshape(*lead, L, g, n),
        chunk_size=cfg.chunk_size,
        D=params["D"].astype(acc),
        inter_chunk=cfg.resolved_inter_chunk(),  # pyright: ignore[reportArgumentType] -- a str checked against the Literal's values at run time
    )
    return gated_rms_norm(y.reshape(*lead, L, d_inner), proj.z, params["norm_scale"], cfg.norm_eps)


def mamba2_block(params: Params, x: Float[Array, "... L D"], cfg: Mamba2Config) -> Float[Array, "... L D"]:
    """The whole block, pre-norm and residual included: ``[..., L, D]`` -> ``[..., L, D]``.

    The reversed direction sees the whole in_proj output flipped along L (global tokens
    included) and its output is flipped back before the two directions are summed.
    """
    d_model = x.shape[-1]
    d_inner, _, _, d_in_proj = _sizes(d_model, cfg)
    if x.ndim < 2 or params["in_proj"]["kernel"].shape != (d_model, d_in_proj):
        raise ValueError(
            f"mamba2_block: x has shape {x.shape}, expected [..., L, D] with in_proj/kernel "
            f"[{d_model}, {d_in_proj}], got {params['in_proj']['kernel'].shape}"
        )
    xn = rms_norm(x, params["norm"]["scale"], cfg.norm_eps)
    kernels = _split_columns(params["in_proj"]["kernel"], in_proj_widths(d_inner, cfg))
    proj = InProj(*(_dense(xn, k) for k in kernels))
    if not cfg.bidirectional:
        y = mamba2_scan_direction(proj, params["mamba_scans_0"], cfg)
    else:
        flipped = InProj(*(jnp.flip(a, axis=-2) for a in proj))
        if cfg.remat_directions:  # a loop of two: the backward holds one direction at a time
            run = remat_after_cotangent(lambda p, w: mamba2_scan_direction(p, w, cfg))
            pair = jax.tree.map(
                lambda *a: jnp.stack(a), (proj, params["mamba_scans_0"]), (flipped, params["mamba_scans_1"])
            )
            y0, y1 = jax.lax.map(lambda pw: run(*pw), pair)
        else:
            y0 = mamba2_scan_direction(proj, params["mamba_scans_0"], cfg)
            y1 = mamba2_scan_direction(flipped, params["mamba_scans_1"], cfg)
        y = y0 + jnp.flip(y1, axis=-2)
    return x + _dense(y, params["out_proj"]["kernel"])


def _torch_default_uniform(key: KeyArray, shape: tuple[int, ...], fan_in: int) -> Float[Array, " ..."]:
    """PyTorch's default Linear/Conv init (kaiming-uniform, a=sqrt(5)): U(+-1/sqrt(fan_in))."""
    bound = 1.0 / fan_in**0.5
    return jax.random.uniform(key, shape, jnp.float32, -bound, bound)


def init_norm(d: int) -> dict[str, Array]:
    """RMSNorm weight ``{"scale": ones [d]}``."""
    return {"scale": jnp.ones((d,), jnp.float32)}


def init_linear(key: KeyArray, fan_in: int, fan_out: int) -> dict[str, Array]:
    """Bias-free linear ``{"kernel": [fan_in, fan_out]}`` with PyTorch's default init."""
    return {"kernel": _torch_default_uniform(key, (fan_in, fan_out), fan_in)}


def init_scan_direction(key: KeyArray, d_model: int, cfg: Mamba2Config) -> dict[str, Array]:
    """Per-direction parameters with Long-LRM's init (facts §1.4).

    ``dt_bias = softplus^-1(dt)``, dt log-uniform in [1e-3, 1e-1] floored at 1e-4;
    ``A_log = log U(1, 16)``; ``D = 1``; gated-norm weight 1; depthwise conv weight and
    bias U(+-1/sqrt(K)) (PyTorch default, fan_in = K).
    """
    d_inner, nh, conv_ch, _ = _sizes(d_model, cfg)
    k_w, k_b, k_dt, k_a = jax.random.split(key, 4)
    K = cfg.d_conv
    u = jax.random.uniform(k_dt, (nh,), jnp.float32)
    dt = jnp.exp(u * (math.log(_DT_MAX) - math.log(_DT_MIN)) + math.log(_DT_MIN))
    dt = jnp.maximum(dt, _DT_INIT_FLOOR)
    lo, hi = _A_INIT_RANGE
    return {
        "conv_kernel": _torch_default_uniform(k_w, (K, conv_ch), K),
        "conv_bias": _torch_default_uniform(k_b, (conv_ch,), K),
        "dt_bias": dt + jnp.log(-jnp.expm1(-dt)),  # inverse of softplus
        "A_log": jnp.log(jax.random.uniform(k_a, (nh,), jnp.float32, lo, hi)),
        "D": jnp.ones((nh,), jnp.float32),
        "norm_scale": jnp.ones((d_inner,), jnp.float32),
    }


def init_mamba2_params(key: KeyArray, d_model: int, cfg: Mamba2Config) -> Params:
    """The full parameter tree of :func:`mamba2_block` (Long-LRM init)."""
    d_inner, _, _, d_in_proj = _sizes(d_model, cfg)
    k_in, k_out, k0, k1 = jax.random.split(key, 4)
    params = {
        "norm": init_norm(d_model),
        "in_proj": init_linear(k_in, d_model, d_in_proj),
        "mamba_scans_0": init_scan_direction(k0, d_model, cfg),
        "out_proj": init_linear(k_out, d_inner, d_model),
    }
    if cfg.bidirectional:
        params["mamba_scans_1"] = init_scan_direction(k1, d_model, cfg)
    return params  # pyright: ignore[reportReturnType] -- Params is a mapping of arrays; dict is invariant


class Mamba2Block(nn.Module):
    """Flax holder of :func:`mamba2_block`'s parameters; ``[B, L, D]`` -> ``[B, L, D]``.

    Parameter paths equal the keys of :func:`init_mamba2_params` (same init).
    """

    d_model: int
    cfg: Mamba2Config

    @nn.compact
    def __call__(self, x: Float[Array, "B L D"]) -> Float[Array, "B L D"]:
        d_inner, _, _, d_in_proj = _sizes(self.d_model, self.cfg)
        if x.shape[-1] != self.d_model:
            raise ValueError(f"Mamba2Block: x has shape {x.shape}, expected [..., L, {self.d_model}]")
        params = {
            "norm": self.param("norm", lambda _: init_norm(self.d_model)),
            "in_proj": self.param("in_proj", init_linear, self.d_model, d_in_proj),
            "mamba_scans_0": self.param("mamba_scans_0", init_scan_direction, self.d_model, self.cfg),
            "out_proj": self.param("out_proj", init_linear, d_inner, self.d_model),
        }
        if self.cfg.bidirectional:
            params["mamba_scans_1"] = self.param("mamba_scans_1", init_scan_direction, self.d_model, self.cfg)
        return mamba2_block(params, x, self.cfg)  # pyright: ignore[reportArgumentType] -- as above
