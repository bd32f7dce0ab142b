"""Backbone: block-pattern parsing, paper parameter count, and the Long-LRM golden run."""

import functools
import os
from dataclasses import replace

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from llrmpp_jax import config as C
from llrmpp_jax.nn import backbone, remat_loops
from llrmpp_jax.nn.backbone import Backbone, count_params, parse_block_pattern
from llrmpp_jax.nn.remat_loops import block_runs, layout_period, remat_blocks
from tests.helpers.environment import GOLDEN, shared_path
from tests.helpers.golden import golden_backbone_config
from tests.helpers.typechecks import unchecked


@pytest.mark.parametrize(
    "pattern, allowed, n, want",
    [
        ("{1T7M}x3", "TM", None, "TMMMMMMM" * 3),
        ("mmmmmmmt", "TM", 24, "MMMMMMMT" * 3),
        ("mmt", "TM", 6, "MMTMMT"),
        ("LLGGG", "LG", None, "LLGGG"),
        ("2L3G", "LG", None, "LLGGG"),
        ("{2M1T}x2M", "TM", None, "MMTMMTM"),
    ],
)
def test_parse_block_pattern(pattern, allowed, n, want):
    # Oracle: the expansions written out by hand.
    assert parse_block_pattern(pattern, allowed, n) == want


@pytest.mark.parametrize("pattern, allowed", [("TXM", "TM"), ("{1T7M}", "TM"), ("", "TM"), ("LLG", "TM")])
def test_parse_block_pattern_rejects(pattern, allowed):
    with pytest.raises(ValueError, match="pattern"):
        parse_block_pattern(pattern, allowed)


def _layer_count_by_hand(d: int, cfg: C.BackboneConfig) -> dict[str, int]:
    """Parameter counts of one block, from the formulas in the reference facts (§1.4, §1.5)."""
    m = cfg.mamba
    di, nh = m.d_inner(d), m.nheads(d)
    conv_ch = di + 2 * m.ngroups * m.d_state
    mamba = d + d * (2 * di + 2 * m.ngroups * m.d_state + nh) + di * d
    mamba += (1 + int(m.bidirectional)) * (conv_ch * m.d_conv + conv_ch + 3 * nh + di)
    t = cfg.transformer
    trans = 2 * d + 4 * d * d + 2 * t.mlp_ratio * d * d + (2 * t.head_dim if t.qk_norm else 0)
    return {"M": mamba, "T": trans}


def test_paper_backbone_parameter_count():
    cfg = C.BackboneConfig()  # the paper preset: D=768, {1T7M}x3, d_state 256, headdim 64
    model = Backbone(cfg, patch_size=8)
    x = jax.ShapeDtypeStruct((1, 2, 16, 16, 9), jnp.float32)
    shapes = jax.eval_shape(model.init, jax.random.key(0), x)["params"]
    got = count_params(shapes)
    per = _layer_count_by_hand(768, cfg)
    want = 576 * 768 + 2 * 768 + 768 + sum(per[k] for k in parse_block_pattern(cfg.pattern, "TM"))
    assert got == want
    assert abs(got - 104e6) / 104e6 < 0.03, got  # paper: backbone ~104M


def _rel_err(got, want) -> float:
    return float(np.max(np.abs(np.asarray(got, np.float64) - want)) / np.max(np.abs(want)))


@pytest.mark.parametrize("dtype, tol", [(jnp.float64, 1e-6), (jnp.float32, 1e-5)])
def test_golden_long_lrm_backbone(dtype, tol):
    """Every block's output matches the official PyTorch run (float64 goldens).

    Tolerance: max|ours - golden| / max|golden|. The golden's own float32 run differs from
    its float64 run by <= 2e-6 on these tensors (config.json), so 1e-5 in float32. In
    float64 everything but the attention softmax runs in float64 (Mamba blocks agree to
    ~1e-14); jax.nn.dot_product_attention always takes its softmax in float32, hence 1e-6.
    """
    from llrmpp_jax.convert.long_lrm import convert_backbone

    sd = dict(np.load(shared_path("golden", "long_lrm_tiny", "state_dict_f64.npz")))
    out = np.load(os.path.join(GOLDEN, "outputs.npz"))
    cfg = golden_backbone_config()
    model = Backbone(cfg, patch_size=8)
    pixels = jnp.asarray(out["pixel_features"], dtype)
    params = convert_backbone(sd, cfg, dtype=np.dtype(dtype))  # pyright: ignore[reportArgumentType] -- any float dtype is taken; the annotation comes from the default
    res, inter = model.apply({"params": params}, pixels, capture_intermediates=True)
    inter = inter["intermediates"]
    assert _rel_err(inter["tokenizer"]["__call__"][0], out["tokenizer_output"]) < tol
    for i in range(6):
        got = inter[f"blocks_{i}"]["__call__"][0]
        assert _rel_err(got, out[f"block{i}_out"]) < tol, i
    merged = jnp.concatenate(inter["merge_0"]["__call__"][0][:2], axis=1)  # pyright: ignore[reportArgumentType] -- sown intermediates: a tuple of arrays per call
    assert _rel_err(merged, out["merge_out"]) < tol
    final = jnp.concatenate([res.global_tokens, res.tokens], axis=1)
    assert _rel_err(final, out["block5_out"]) < tol
    assert res.grid == (2, 3)


def test_backbone_rejects_bad_sizes():
    model = Backbone(golden_backbone_config(), patch_size=8)
    with pytest.raises(ValueError, match="multiple of 16"):
        jax.eval_shape(model.init, jax.random.key(0), jax.ShapeDtypeStruct((1, 2, 24, 48, 9), jnp.float32))
    with pytest.raises(ValueError, match=r"\[B, V, H, W, C\]"), unchecked():
        jax.eval_shape(model.init, jax.random.key(0), jax.ShapeDtypeStruct((2, 32, 48, 9), jnp.float32))


def test_block_runs_and_period():
    # Oracle: the runs and periods read off by hand.
    assert block_runs("TMMMT") == [(0, "T", 1), (1, "M", 3), (4, "T", 1)]
    assert block_runs("MMTMMT") == [(0, "M", 2), (2, "T", 1), (3, "M", 2), (5, "T", 1)]
    assert [layout_period(k) for k in ("M", "MMM", "TMMTMM", "TMMTM", "TMMMMMMM" * 3)] == [1, 1, 3, 5, 8]


@pytest.mark.parametrize(
    "cfg, size, calls",
    [
        pytest.param(
            replace(golden_backbone_config(), mamba=C.Mamba2Config(d_state=16, headdim=16, chunk_size=4)),
            (32, 48),
            ["MMT", "MM", "M", "T"] * 2,
            marks=pytest.mark.slow,
        ),
        (
            C.BackboneConfig(
                dims=(32,),
                pattern="{1T2M}x2",
                num_layers=6,
                mamba=C.Mamba2Config(d_state=8, headdim=16, chunk_size=4),
                transformer=C.TransformerConfig(head_dim=16),
            ),
            (16, 24),
            ["TMMTMM", "TMM", "T", "MM", "M"],
        ),
    ],
    ids=["merge_mmt", "1T2Mx2"],
)
def test_remat_loops_match_unrolled(cfg, size, calls, key, monkeypatch):
    """With remat, the blocks run as (nested) lax.scans over stacked parameters: the outputs
    and the gradients of every parameter and of the pixels equal the unrolled blocks'
    (float32, <= 1e-5 relative), on the same randomly perturbed parameters."""
    k_init, k_noise, k_x, k_ct = jax.random.split(key, 4)
    pixels = jax.random.normal(k_x, (1, 2, *size, 9), jnp.float32)
    unrolled, looped = Backbone(cfg, patch_size=8), Backbone(replace(cfg, remat=True), patch_size=8)
    params = jax.jit(unrolled.init)(k_init, pixels)["params"]
    leaves, tree = jax.tree.flatten(params)
    noise = jax.random.split(k_noise, len(leaves))
    params = tree.unflatten([p + 0.1 * jax.random.normal(k, p.shape, p.dtype) for p, k in zip(leaves, noise)])
    assert jax.tree.structure(jax.eval_shape(looped.init, k_init, pixels)["params"]) == tree  # same layout

    def loss(model, p, x):
        out = model.apply({"params": p}, x)
        y = jnp.concatenate([out.global_tokens, out.tokens], axis=1)
        return jnp.sum(y * jax.random.normal(k_ct, y.shape, y.dtype)), y

    grad = lambda m: jax.jit(jax.grad(functools.partial(loss, m), argnums=(0, 1), has_aux=True))  # noqa: E731
    (gp_u, gx_u), y_u = grad(unrolled)(params, pixels)
    (gp_s, gx_s), y_s = grad(looped)(params, pixels)
    assert _rel_err(y_s, np.asarray(y_u, np.float64)) < 1e-5
    assert _rel_err(gx_s, np.asarray(gx_u, np.float64)) < 1e-5
    for path, g_u in jax.tree_util.tree_leaves_with_path(gp_u):
        g_s = functools.reduce(lambda t, k: t[k.key], path, gp_s)
        assert _rel_err(g_s, np.asarray(g_u, np.float64)) < 1e-5, jax.tree_util.keystr(path)
    # The looped model really recurses into periods and runs (each level traced once).
    seen = []
    for module in (backbone, remat_loops):
        monkeypatch.setattr(module, "remat_blocks", lambda k, *a: seen.append(k) or remat_blocks(k, *a))
    jax.eval_shape(lambda p: unrolled.apply({"params": p}, pixels), params)
    assert seen == []
    jax.eval_shape(lambda p: looped.apply({"params": p}, pixels), params)
    assert seen == calls
