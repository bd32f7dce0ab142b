"""The splash-attention path compiled for a TPU chip on this CPU (libtpu's compile-only
devices): Mosaic accepts the kernels at a ragged length and a small head dim, forward and
gradient, and the program holds the kernels as TPU custom calls (one forward; the gradient's
forward, dq and dkv kernels), which the HLO estimate counts by their matrix products over
the padded length (oracle: 2 x M x N x K per product; forward 2 products, dq 3, dkv 4)."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

pytest.importorskip("libtpu", reason="the TPU compiler (libtpu) is in the test extra: pip install -e '.[test]'")

from jax.sharding import Mesh, NamedSharding, PartitionSpec  # noqa: E402

from llrmpp_jax.nn.attention import multi_head_attention  # noqa: E402
from llrmpp_jax.plan import targets  # noqa: E402
from llrmpp_jax.plan.hlo_cost import Chip, estimate_hlo  # noqa: E402


@pytest.mark.parametrize(("grad", "kernels", "products"), [(False, 1, 2), (True, 3, 2 + 3 + 4)])
def test_splash_compiles_for_v5e_at_a_ragged_length(grad, kernels, products):
    mesh = Mesh(np.asarray(targets.compile_devices(targets.target("v5e"))[:1]), ("batch",))
    sds = jax.ShapeDtypeStruct((2, 200, 2, 16), jnp.bfloat16, sharding=NamedSharding(mesh, PartitionSpec()))
    fn = lambda q, k, v: multi_head_attention(q, k, v, implementation="splash")  # noqa: E731
    if grad:
        forward = fn
        fn = jax.grad(lambda q, k, v: jnp.sum(forward(q, k, v).astype(jnp.float32)), argnums=(0, 1, 2))
    with jax.enable_x64(False), jax.numpy_dtype_promotion("standard"):
        compiled = jax.jit(fn).lower(sds, sds, sds).compile()
    text = compiled.as_text()
    assert text is not None and text.count('custom_call_target="tpu_custom_call"') == kernels
    heads, padded, hd = 2 * 2, 256, 16  # batch x heads; 200 tokens in 256-token blocks
    est = estimate_hlo(text, Chip(peak_flops=1e12, hbm_bytes_per_s=1e9, ici_bytes_per_s=1e9))
    assert est.flops == products * 2 * heads * padded * padded * hd
    assert compiled.memory_analysis().temp_size_in_bytes < 2**24  # pyright: ignore[reportOptionalMemberAccess] -- the TPU compiler reports memory
