"""TransformerBlock against a float64 NumPy oracle and the Long-LRM golden blocks 2 and 5."""

import json
import os

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from llrmpp_jax.config import TransformerConfig
from llrmpp_jax.convert.table import Rule, convert_state_dict, linear
from llrmpp_jax.nn.transformer import TransformerBlock
from tests.helpers.environment import shared_path
from tests.oracles.attention import attention_module_oracle, gelu, randomize, rel_err
from tests.oracles.local_attention import module_mask_bias


def layer_norm(x: np.ndarray, scale: np.ndarray, eps: float = 1e-5) -> np.ndarray:
    mu = x.mean(-1, keepdims=True)
    return (x - mu) / np.sqrt(((x - mu) ** 2).mean(-1, keepdims=True) + eps) * scale


def block_oracle(p, x, cfg: TransformerConfig, grid=None, num_neighbours=None):
    """Float64 pre-LN block: x + attn(LN1 x), then + fc2(gelu(fc1(LN2 x)))."""
    f = lambda a: np.asarray(a, np.float64)  # noqa: E731
    x = f(x)
    x = x + attention_module_oracle(
        p["attn"],
        layer_norm(x, f(p["norm1"]["scale"]), cfg.norm_eps),
        cfg.head_dim,
        cfg.qk_norm,
        None if grid is None else module_mask_bias(grid, num_neighbours),
        eps=cfg.norm_eps,
    )
    y = layer_norm(x, f(p["norm2"]["scale"]), cfg.norm_eps)
    return x + gelu(y @ f(p["mlp"]["fc1"]["kernel"])) @ f(p["mlp"]["fc2"]["kernel"])


@pytest.mark.parametrize("qk_norm", [False, True])
def test_global_block_matches_oracle(key, rng, qk_norm):
    cfg = TransformerConfig(head_dim=8, qk_norm=qk_norm)
    x = rng.normal(size=(2, 7, 16)).astype(np.float32)
    block = TransformerBlock(dim=16, cfg=cfg)
    params = block.init(key, x)["params"]
    assert params["mlp"]["fc1"]["kernel"].shape == (16, 64) and params["mlp"]["fc2"]["kernel"].shape == (64, 16)  # pyright: ignore[reportAttributeAccessIssue] -- a leaf of the params tree is an array
    assert set(params) == {"norm1", "attn", "norm2", "mlp"}
    params = randomize(params, rng)
    got = jax.jit(block.apply)({"params": params}, x)
    assert got.dtype == jnp.float32
    assert rel_err(got, block_oracle(params, x, cfg)) < 1e-5


def test_local_block_matches_oracle(key, rng):
    cfg = TransformerConfig(head_dim=8, qk_norm=True)
    h, w, k = 4, 5, 16
    x = rng.normal(size=(2, h * w, 16)).astype(np.float32)
    block = TransformerBlock(dim=16, cfg=cfg, attention="local", grid=(h, w), num_neighbours=k)
    params = randomize(block.init(key, x)["params"], rng)
    assert "rel_bias" in params["attn"]
    got = block.apply({"params": params}, x)
    assert rel_err(got, block_oracle(params, x, cfg, grid=(h, w), num_neighbours=k)) < 1e-5


def test_block_bfloat16_compute(key, rng):
    """dtype=bfloat16 computes in bf16 and stays close to the float64 oracle."""
    cfg = TransformerConfig(head_dim=8, qk_norm=True)
    x = rng.normal(size=(2, 12, 16)).astype(np.float32)
    params = randomize(TransformerBlock(16, cfg).init(key, x)["params"], rng, std=0.2)
    want = block_oracle(params, x, cfg)
    for attention, grid in (("global", None), ("local", (3, 4))):
        block = TransformerBlock(16, cfg, attention, grid, num_neighbours=64, dtype=jnp.bfloat16)  # pyright: ignore[reportArgumentType] -- a str checked against the Literal's values at run time
        if attention == "local":
            p = randomize(block.init(key, x)["params"], rng, std=0.2)
            want = block_oracle(p, x, cfg, grid=grid, num_neighbours=64)
        else:
            p = params
        got = jax.jit(block.apply)({"params": p}, jnp.asarray(x, jnp.bfloat16))
        assert got.dtype == jnp.bfloat16
        assert rel_err(got, want) < 3e-2


def test_block_errors(key):
    x = jnp.zeros((1, 6, 16), jnp.float32)
    cfg = TransformerConfig(head_dim=8)
    with pytest.raises(ValueError, match=r"attention must be 'global' or 'local', got 'sparse'"):
        TransformerBlock(16, cfg, attention="sparse").init(key, x)  # pyright: ignore[reportArgumentType] -- a bad value on purpose: the test wants its error
    with pytest.raises(ValueError, match=r"attention='local' needs grid"):
        TransformerBlock(16, cfg, attention="local").init(key, x)
    with pytest.raises(ValueError, match=r"dim=16 is not a multiple of head_dim=6"):
        TransformerBlock(16, TransformerConfig(head_dim=6)).init(key, x)


@pytest.mark.parametrize("block_idx,prev", [(2, "block1_out"), (5, "block4_out")])
def test_long_lrm_golden_block(key, block_idx, prev):
    """Official Long-LRM TransformerBlock (float64 run) from its converted state_dict.

    Tolerance: max|ours - golden| / max|golden| below the float32-vs-float64 figure stated
    in config.json for the same code run in float32.
    """
    folder = shared_path("golden", "long_lrm_tiny")
    with open(os.path.join(folder, "config.json")) as fh:
        config = json.load(fh)
    tol = config["precision"]["float32_run_of_same_code_vs_golden_max_rel_diff"]
    head_dim = config["transformer"]["head_dim"]
    with np.load(os.path.join(folder, "outputs.npz")) as z:
        x = z[prev]
        golden = {name: z[f"block{block_idx}.{name}"] for name in ("norm1_out", "attn_out", "norm2_out", "mlp_out")}
        golden["out"] = z[f"block{block_idx}_out"]
    with np.load(os.path.join(folder, "state_dict.npz")) as z:
        state = {k: z[k] for k in z.files}

    dim = x.shape[-1]
    block = TransformerBlock(dim=dim, cfg=TransformerConfig(head_dim=head_dim, qk_norm=False))
    x32 = jnp.asarray(x, jnp.float32)
    pre = rf"processor\.blocks\.{block_idx}\."
    rules = [
        Rule(pre + r"norm1\.weight", "norm1/scale"),
        Rule(pre + r"norm2\.weight", "norm2/scale"),
        Rule(pre + r"attn\.qkv\.weight", "attn/qkv/kernel", linear),
        Rule(pre + r"attn\.proj\.weight", "attn/proj/kernel", linear),
        Rule(pre + r"mlp\.fc1\.weight", "mlp/fc1/kernel", linear),
        Rule(pre + r"mlp\.fc2\.weight", "mlp/fc2/kernel", linear),
    ]
    params = convert_state_dict(
        state,
        rules,
        expected=jax.eval_shape(block.init, key, x32)["params"],
        keep_prefixes=(f"processor.blocks.{block_idx}.",),
    )
    out, state_vars = block.apply({"params": params}, x32, capture_intermediates=True)
    inter = state_vars["intermediates"]
    ours = {
        "norm1_out": inter["norm1"]["__call__"][0],
        "attn_out": inter["attn"]["__call__"][0],
        "norm2_out": inter["norm2"]["__call__"][0],
        "mlp_out": inter["mlp"]["__call__"][0],
        "out": out,
    }
    for name, want in golden.items():
        assert ours[name].shape == want.shape, name
        err = rel_err(ours[name], want)
        assert err < tol, f"{name}: relative error {err:.3g} >= {tol:.3g}"
