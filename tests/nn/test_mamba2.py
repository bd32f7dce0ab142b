"""Long-LRM bidirectional Mamba2 block (llrmpp_jax/nn/mamba2.py) and its conversion rules.

Oracles: the official PyTorch code's float64 golden activations (mamba2_block.npz and the
Mamba blocks of outputs.npz, parameters loaded through ``convert/long_lrm.py``), torch's
grouped ``conv1d``, NumPy formulas, the measured Long-LRM parameter counts (facts §1.1)
and the init distributions of facts §1.4 (Kolmogorov-Smirnov tests).

Golden tolerance (float32 port vs float64 golden): for every compared array,
``max|ours - golden| <= 1e-5 * max|golden|`` *and* ``<= 3x`` the error the official code
itself makes when run in float32 (config.json: ``mamba2_block_fixture.f32_vs_f64`` and
``precision.float32_run_of_same_code_vs_golden``); ours is typically 0.5-1x of it.
"""

import dataclasses
import functools
import json
import os
import re

import jax
import jax.numpy as jnp
import numpy as np
import pytest
import scipy.stats
import torch

from llrmpp_jax.config import Mamba2Config
from llrmpp_jax.convert.long_lrm import mamba2_block_rules
from llrmpp_jax.convert.table import conv1d_depthwise, convert_state_dict
from llrmpp_jax.nn.mamba2 import (
    InProj,
    Mamba2Block,
    causal_depthwise_conv1d,
    gated_rms_norm,
    in_proj_widths,
    init_mamba2_params,
    mamba2_block,
    mamba2_scan_direction,
)
from llrmpp_jax.nn.norms import rms_norm
from tests.helpers.environment import GOLDEN, shared_path
from tests.helpers.typechecks import unchecked


def _golden_config() -> dict:
    with open(shared_path("golden", "long_lrm_tiny", "config.json")) as f:
        return json.load(f)


def _assert_golden(name: str, ours, golden: np.ndarray, f32_abs_err: float) -> None:
    err = float(np.abs(np.asarray(ours, np.float64) - golden).max())
    scale = float(np.abs(golden).max())
    assert err <= 1e-5 * scale, f"{name}: max abs err {err:.3g} > 1e-5 * {scale:.3g}"
    assert err <= 3 * f32_abs_err, f"{name}: max abs err {err:.3g} > 3 x upstream f32 err {f32_abs_err:.3g}"


@functools.partial(jax.jit, static_argnums=0)
def _run(module: Mamba2Block, params, x) -> dict:
    """The golden files' per-block internals, recomputed from the pure functions, and the
    module's output."""
    cfg = module.cfg
    norm_out = rms_norm(x, params["norm"]["scale"], cfg.norm_eps)
    in_proj_out = norm_out @ params["in_proj"]["kernel"]
    bounds = np.cumsum(in_proj_widths(params["out_proj"]["kernel"].shape[0], cfg))[:-1]
    blocks = jnp.split(in_proj_out, bounds, axis=-1)
    scan0 = mamba2_scan_direction(InProj(*blocks), params["mamba_scans_0"], cfg)
    scan1_rev = mamba2_scan_direction(InProj(*(b[:, ::-1] for b in blocks)), params["mamba_scans_1"], cfg)
    out_proj_in = scan0 + scan1_rev[:, ::-1]
    return {
        "norm_out": norm_out,
        "in_proj_out": in_proj_out,
        "scan0_out": scan0,
        "scan1_out_reversed": scan1_rev,
        "out_proj_in": out_proj_in,
        "out_proj_out": out_proj_in @ params["out_proj"]["kernel"],
        "output": module.apply({"params": params}, x),
    }


def _load_block(state_dict, prefix: str, d_model: int, cfg: Mamba2Config, x):
    """Convert ``prefix``-keyed PyTorch tensors strictly against the module's own param tree."""
    module = Mamba2Block(d_model=d_model, cfg=cfg)
    expected = jax.eval_shape(module.init, jax.random.key(0), x)["params"]
    params = convert_state_dict(
        state_dict,
        mamba2_block_rules(re.escape(prefix)),
        expected=expected,
        keep_prefixes=(prefix + "norm.", prefix + "mamba."),
    )
    return module, jax.tree_util.tree_map(jnp.asarray, params)


def test_causal_conv_matches_torch(rng):
    """Against ``torch.nn.functional.conv1d(groups=C, padding=K-1)`` truncated to L outputs,
    with the weight taken through the conversion transform (C, 1, K) -> (K, C): 1e-6."""
    x = rng.standard_normal((2, 11, 6)).astype(np.float32)
    w = rng.standard_normal((6, 1, 4)).astype(np.float32)
    b = rng.standard_normal(6).astype(np.float32)
    want = (
        torch.nn.functional.conv1d(
            torch.from_numpy(x).transpose(1, 2), torch.from_numpy(w), torch.from_numpy(b), padding=3, groups=6
        )[..., :11]
        .transpose(1, 2)
        .numpy()
    )
    got = causal_depthwise_conv1d(jnp.asarray(x), jnp.asarray(conv1d_depthwise(w)), jnp.asarray(b))
    np.testing.assert_allclose(np.asarray(got), want, rtol=1e-6, atol=1e-6)


def test_causal_conv_gradients_match_torch(rng):
    """Gradients of x, kernel and bias against torch autograd of the same grouped conv1d, in
    float64 on a batch with two leading axes and a random cotangent: 1e-12."""
    x = rng.standard_normal((2, 3, 9, 5))
    w = rng.standard_normal((5, 1, 4))
    b = rng.standard_normal(5)
    ct = rng.standard_normal((2, 3, 9, 5))
    xt, wt, bt = (torch.tensor(a, requires_grad=True) for a in (x, w, b))
    yt = torch.nn.functional.conv1d(xt.reshape(6, 9, 5).transpose(1, 2), wt, bt, padding=3, groups=5)
    (yt[..., :9].transpose(1, 2).reshape(2, 3, 9, 5) * torch.from_numpy(ct)).sum().backward()
    _, vjp = jax.vjp(causal_depthwise_conv1d, jnp.asarray(x), jnp.asarray(conv1d_depthwise(w)), jnp.asarray(b))
    gx, gk, gb = vjp(jnp.asarray(ct))
    np.testing.assert_allclose(np.asarray(gx), xt.grad.numpy(), rtol=1e-12, atol=1e-12)  # pyright: ignore[reportOptionalMemberAccess] -- torch fills .grad in the backward() above
    np.testing.assert_allclose(np.asarray(gk), conv1d_depthwise(wt.grad.numpy()), rtol=1e-12, atol=1e-12)  # pyright: ignore[reportOptionalMemberAccess] -- torch fills .grad in the backward() above
    np.testing.assert_allclose(np.asarray(gb), bt.grad.numpy(), rtol=1e-12, atol=1e-12)  # pyright: ignore[reportOptionalMemberAccess] -- torch fills .grad in the backward() above


def test_gated_rms_norm_matches_formula(rng):
    """mamba_ssm rms_norm_ref, norm_before_gate=False: (y*silu(z)) * rsqrt(mean(.^2)+eps) * w."""
    y, z = rng.standard_normal((2, 3, 2, 16)).astype(np.float32)
    w = rng.standard_normal(16).astype(np.float32)
    yd, zd = y.astype(np.float64), z.astype(np.float64)
    gated = yd * zd / (1 + np.exp(-zd))
    want = gated / np.sqrt(np.mean(gated**2, -1, keepdims=True) + 1e-5) * w
    got = gated_rms_norm(jnp.asarray(y), jnp.asarray(z), jnp.asarray(w), 1e-5)
    np.testing.assert_allclose(np.asarray(got), want, rtol=2e-6, atol=2e-6)


def test_auto_inter_chunk_is_the_fastest_form_on_each_backend():
    """The default resolves to the fused scan on CPU (bench_scan.json: ~2x the associative
    form there) and to the low-memory sequential one on accelerators; explicit forms stay."""
    cfg = Mamba2Config()
    assert cfg.inter_chunk == "auto"
    assert cfg.resolved_inter_chunk("cpu") == "fused" == cfg.resolved_inter_chunk()  # this suite runs on CPU
    assert cfg.resolved_inter_chunk("gpu") == "sequential" == cfg.resolved_inter_chunk("tpu")
    for form in ("associative", "sequential", "fused"):
        assert Mamba2Config(inter_chunk=form).resolved_inter_chunk("cpu") == form


@pytest.mark.parametrize("inter_chunk", ["auto", "associative", "sequential", "fused"])
def test_block_matches_golden_fixture(inter_chunk):
    """mamba2_block.npz: d_model 64, d_state 16, headdim 64 (2 heads), chunk 8, L = 37,
    with each form of the SSD scan."""
    z = np.load(shared_path("golden", "long_lrm_tiny", "mamba2_block.npz"))
    f32_err = _golden_config()["mamba2_block_fixture"]["f32_vs_f64"]
    cfg = Mamba2Config(d_state=16, headdim=64, chunk_size=8, inter_chunk=inter_chunk)
    x = jnp.asarray(z["input"], jnp.float32)
    module, params = _load_block(z, "", 64, cfg, x)
    for name, ours in _run(module, params, x).items():
        _assert_golden(name, ours, z[name], f32_err[name]["max_abs_diff"])


@pytest.mark.parametrize(
    "block, input_key", [(0, "processor_input"), (1, "block0_out"), (3, "merge_out"), (4, "block3_out")]
)
def test_backbone_blocks_match_golden(block, input_key):
    """outputs.npz Mamba blocks (headdim 16, d_state 16) given the previous block's output;
    blocks 3/4 run at d_model 64 after the merge. Chunk 8 pads L = 50 -> 56 and 14 -> 16."""
    out = np.load(shared_path("golden", "long_lrm_tiny", "outputs.npz"))
    sd = np.load(os.path.join(GOLDEN, "state_dict.npz"))
    f32_err = _golden_config()["precision"]["float32_run_of_same_code_vs_golden"]
    cfg = Mamba2Config(d_state=16, headdim=16, chunk_size=8)
    x = jnp.asarray(out[input_key], jnp.float32)
    prefix = f"processor.blocks.{block}."
    module, params = _load_block(sd, prefix, x.shape[-1], cfg, x)
    for name, ours in _run(module, params, x).items():
        key = f"block{block}_out" if name == "output" else f"block{block}.{name}"
        _assert_golden(key, ours, out[key], f32_err[key]["max_abs_diff"])


def test_block_bf16_activations_track_golden():
    """bf16 activations (float32 params, float32 accumulation): the output stays within
    bf16 rounding of the float64 golden, 2e-2 * max|golden|."""
    z = np.load(shared_path("golden", "long_lrm_tiny", "mamba2_block.npz"))
    cfg = Mamba2Config(d_state=16, headdim=64, chunk_size=8)
    x = jnp.asarray(z["input"], jnp.bfloat16)
    module, params = _load_block(z, "", 64, cfg, x)
    out = jax.jit(module.apply)({"params": params}, x)
    assert out.dtype == jnp.bfloat16
    err = np.abs(np.asarray(out.astype(jnp.float32), np.float64) - z["output"]).max()
    assert err <= 2e-2 * np.abs(z["output"]).max()


def test_remat_directions_matches_plain_block(key):
    """``remat_directions``: the two directions as a remat'd loop of two; output and the
    gradients of every parameter and of x equal the plain block's (float32, <= 1e-5
    relative), on random parameters (init perturbed) and inputs."""
    cfg = Mamba2Config(d_state=8, headdim=8, chunk_size=4)
    k_p, k_n, k_x, k_ct = jax.random.split(key, 4)
    params = init_mamba2_params(k_p, 16, cfg)
    leaves, tree = jax.tree.flatten(params)
    params = tree.unflatten(
        [p + 0.1 * jax.random.normal(k, p.shape, p.dtype) for p, k in zip(leaves, jax.random.split(k_n, len(leaves)))]
    )
    x = jax.random.normal(k_x, (2, 11, 16), jnp.float32)
    ct = jax.random.normal(k_ct, x.shape, jnp.float32)

    @functools.partial(jax.jit, static_argnums=0)
    def value_and_vjp(c, p, h):
        y, vjp = jax.vjp(lambda p, h: mamba2_block(p, h, c), p, h)
        return y, *vjp(ct)

    results = [value_and_vjp(c, params, x) for c in (cfg, dataclasses.replace(cfg, remat_directions=True))]
    for (path, want), got in zip(jax.tree_util.tree_leaves_with_path(results[0]), jax.tree.leaves(results[1])):
        err = float(jnp.max(jnp.abs(got - want)) / jnp.max(jnp.abs(want)))
        assert err <= 1e-5, (jax.tree_util.keystr(path), err)


def test_rules_with_named_group_prefix():
    """A backbone-style table (``processor.blocks.{i}.`` -> ``blocks_{i}/``) converts all four
    Mamba blocks of state_dict.npz at once, each leaf equal to the transformed tensor."""
    sd = np.load(shared_path("golden", "long_lrm_tiny", "state_dict.npz"))
    rules = mamba2_block_rules(r"processor\.blocks\.(?P<i>\d+)\.", "blocks_{i}/")
    mamba_keys = tuple(f"processor.blocks.{i}.{part}" for i in (0, 1, 3, 4) for part in ("norm.", "mamba."))
    params = convert_state_dict(sd, rules, keep_prefixes=mamba_keys)
    assert sorted(params) == ["blocks_0", "blocks_1", "blocks_3", "blocks_4"]
    blk, torch_key = params["blocks_3"], "processor.blocks.3.mamba.{}".format
    np.testing.assert_array_equal(blk["in_proj"]["kernel"], sd[torch_key("in_proj.weight")].T)
    conv_w = sd[torch_key("mamba_scans.1.conv1d.weight")]
    np.testing.assert_array_equal(blk["mamba_scans_1"]["conv_kernel"], conv_w[:, 0].T)
    np.testing.assert_array_equal(blk["mamba_scans_0"]["A_log"], sd[torch_key("mamba_scans.0.A_log")])
    norm_w = sd[torch_key("mamba_scans.0.norm.weight")]
    np.testing.assert_array_equal(blk["mamba_scans_0"]["norm_scale"], norm_w)


def test_unidirectional_block_is_forward_half_of_golden():
    """bidirectional=False: x + out_proj(scan0), with scan0 and out_proj from the golden fixture."""
    z = np.load(shared_path("golden", "long_lrm_tiny", "mamba2_block.npz"))
    cfg = Mamba2Config(d_state=16, headdim=64, chunk_size=8, bidirectional=False)
    forward_only = {k: z[k] for k in z.files if "mamba_scans.1." not in k and k.startswith(("norm.", "mamba."))}
    module = Mamba2Block(d_model=64, cfg=cfg)
    x = jnp.asarray(z["input"], jnp.float32)
    expected = jax.eval_shape(module.init, jax.random.key(0), x)["params"]
    params = convert_state_dict(forward_only, mamba2_block_rules(), expected=expected)
    got = jax.jit(mamba2_block, static_argnums=2)(jax.tree_util.tree_map(jnp.asarray, params), x, cfg)
    want = z["input"] + z["scan0_out"] @ z["mamba.out_proj.weight"].astype(np.float64).T
    assert np.abs(np.asarray(got, np.float64) - want).max() <= 1e-5 * np.abs(want).max()


@pytest.mark.parametrize("d_model, count", [(256, 537_904), (1024, 6_879_424)])
def test_parameter_count_matches_long_lrm(d_model, count):
    """Measured Long-LRM Mamba block sizes (facts §1.1), d_state 256, headdim 64."""
    module = Mamba2Block(d_model=d_model, cfg=Mamba2Config())
    x = jax.ShapeDtypeStruct((1, 8, d_model), jnp.float32)
    shapes = jax.eval_shape(module.init, jax.random.key(0), x)
    assert sum(int(np.prod(s.shape)) for s in jax.tree_util.tree_leaves(shapes)) == count


def test_init_distributions(key):
    """facts §1.4: softplus(dt_bias) log-uniform on [1e-3, 1e-1]; exp(A_log) ~ U(1, 16);
    D, norm weights = 1; in_proj/out_proj/conv ~ U(+-1/sqrt(fan_in)). KS p-value > 1e-3."""
    cfg = Mamba2Config(d_state=8, headdim=1, expand=2)
    d = 1024  # 2048 heads of size 1 give 2048 samples of dt_bias and A_log per direction
    p = jax.tree_util.tree_map(np.asarray, jax.jit(init_mamba2_params, static_argnums=(1, 2))(key, d, cfg))
    scan = p["mamba_scans_0"]
    dt = np.log(np.logaddexp(0.0, scan["dt_bias"].astype(np.float64)))
    log_uniform = scipy.stats.uniform(np.log(1e-3), np.log(1e-1) - np.log(1e-3))
    assert scipy.stats.kstest(dt, log_uniform.cdf).pvalue > 1e-3
    assert scipy.stats.kstest(np.exp(scan["A_log"]), scipy.stats.uniform(1, 15).cdf).pvalue > 1e-3
    fans = [
        (p["in_proj"]["kernel"], d),
        (p["out_proj"]["kernel"], 2 * d),
        (scan["conv_kernel"], 4),
        (scan["conv_bias"], 4),
    ]
    for w, fan_in in fans:
        bound = fan_in**-0.5
        assert scipy.stats.kstest(w.ravel()[:20000], scipy.stats.uniform(-bound, 2 * bound).cdf).pvalue > 1e-3
    for ones in (scan["D"], scan["norm_scale"], p["norm"]["scale"]):
        np.testing.assert_array_equal(ones, 1.0)
    # the two directions are initialised independently
    assert not np.allclose(p["mamba_scans_1"]["A_log"], scan["A_log"])


def test_bad_inputs_raise(key):
    cfg = Mamba2Config(d_state=4, headdim=8, chunk_size=4)
    module = Mamba2Block(d_model=16, cfg=cfg)
    shapes = jax.eval_shape(module.init, key, jnp.zeros((1, 5, 16)))
    params = jax.tree_util.tree_map(lambda s: jnp.zeros(s.shape, s.dtype), shapes)
    with pytest.raises(ValueError, match="expected \\[..., L, 16\\]"):
        module.apply(params, jnp.zeros((1, 5, 12)))
    with pytest.raises(ValueError, match="in_proj blocks"):
        mamba2_scan_direction(InProj(*(jnp.zeros((5, 2)),) * 5), params["params"]["mamba_scans_0"], cfg)
    with pytest.raises(ValueError, match="kernel"), unchecked():
        causal_depthwise_conv1d(jnp.zeros((5, 3)), jnp.zeros((4, 2)), jnp.zeros(3))


def test_bad_scan_settings_raise_one_line():
    with pytest.raises(ValueError, match=r"^Mamba2Config.inter_chunk must be .* got 'dense'$"), unchecked():
        Mamba2Config(inter_chunk="dense")  # pyright: ignore[reportArgumentType] -- a bad value on purpose: the test wants its error
    with pytest.raises(ValueError, match=r"^Mamba2Config.chunk_size must be >= 1, got 0$"):
        Mamba2Config(chunk_size=0)
