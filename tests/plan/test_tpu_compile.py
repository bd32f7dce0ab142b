"""The tiny model compiled for a TPU chip on this CPU with libtpu's compile-only devices:
it compiles, fits, takes the TPU kernels, and the estimate's FLOPs match an independent count.

Oracle for the FLOPs: ``benchmarks.measure.matmul_flops`` counts the matrix products of the
traced program (jaxpr, before XLA); the estimate counts them in the TPU compiler's optimised
HLO, where batched products have become convolutions, and the splash attention kernels by
their products over their 128-token blocks. The two must agree to 1%, plus that padding.
"""

import jax
import jax.numpy as jnp
import pytest

pytest.importorskip("libtpu", reason="the TPU compiler (libtpu) is in the test extra: pip install -e '.[test]'")

from llrmpp_jax import config as C  # noqa: E402
from llrmpp_jax.errors import UserError  # noqa: E402
from llrmpp_jax.plan.planner import Program, compile_row, plan, program  # noqa: E402
from llrmpp_jax.plan.targets import target  # noqa: E402

V5E = target("v5e")


@pytest.mark.parametrize("name", ["tiny_reconstruct", "tiny_render"])
def test_tiny_programs_compile_and_fit_on_v5e(name):
    row = compile_row(program(name), V5E)
    assert row["program"] == name and row["compiled"], row.get("error")
    assert row["fits"] and 0 < row["hbm_needed_bytes"] < 2**30
    # The splash attention kernels also multiply the padding of their 128-token blocks (the
    # tiny model's short sequences: a few percent of its products).
    assert row["model_flops"] * 0.99 <= row["estimate"]["flops"] <= 1.1 * row["model_flops"]
    assert row["estimate"]["seconds"] >= row["matmul_limit_s"] > 0


def test_tiny_train_step_compiles_and_fits_on_v5e():
    """The trainer's step (loss, gradient, pmean, guarded AdamW) through the TPU compiler. Its
    matrix products are at least the loss's forward and backward (the jaxpr count, no remat)
    and at most twice that (remat recomputes forwards; XLA may fold a few products)."""
    row = compile_row(program("tiny_train"), V5E)
    assert row["program"] == "tiny_train" and row["compiled"], row.get("error")
    assert row["fits"] and row["memory"]["alias"] > 0  # the donated state is updated in place
    assert row["model_flops"] * 0.99 <= row["estimate"]["flops"] <= 2.0 * row["model_flops"]
    assert row["estimate"]["loops"] > 0 and row["estimate"]["seconds"] >= row["matmul_limit_s"]


def test_tpu_path_picks_the_splash_kernel_and_sequential_scan():
    cfg = C.for_accelerators(C.tiny(), backend="tpu")
    assert cfg.backbone.transformer.attention_impl == "splash"
    assert cfg.decoder.transformer.attention_impl == "splash"
    assert cfg.backbone.mamba.inter_chunk == "sequential"
    assert C.for_accelerators(C.tiny(), backend="gpu").backbone.transformer.attention_impl == "cudnn"


def test_a_program_over_the_chips_hbm_is_a_row_saying_what_it_needs():
    def build(mesh, backend):
        x = jax.ShapeDtypeStruct(
            (2**20,), jnp.float32, sharding=jax.sharding.NamedSharding(mesh, jax.sharding.PartitionSpec())
        )
        return jax.jit(lambda x: jnp.broadcast_to(x[None], (5 * 2**10, 2**20)) * 2.0), (x,)  # 20 GiB out

    row = compile_row(Program("big", "20 GiB result", build), V5E)
    assert not row["compiled"] and row["fits"] is False
    assert row["needs_bytes"] == pytest.approx(20 * 2**30, rel=0.01)
    assert 15 * 2**30 < row["hbm_available_bytes"] <= 16 * 2**30


@pytest.mark.parametrize(
    ("programs", "targets", "known"),
    [
        (["no_such_program"], ["v5e"], "reconstruct_32"),
        (["tiny"], ["v9z"], "v5p"),
    ],
)
def test_unknown_names_are_one_line_listing_the_known_ones(programs, targets, known):
    with pytest.raises(UserError) as e:
        plan(programs, targets, log=lambda _: None)
    assert known in str(e.value) and "\n" not in str(e.value)
