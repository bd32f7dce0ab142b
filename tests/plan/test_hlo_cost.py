"""The HLO roofline estimate against counts worked out by hand, on programs compiled for this CPU.

Oracles: a matrix product's FLOPs are 2 x M x N x K; a loop of L steps does L times its body;
an elementwise op moves its operand and its result; a conditional costs its dearer branch.
"""

import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from llrmpp_jax.plan.hlo_cost import Chip, estimate_hlo, hbm_bytes, parse_module

CHIP = Chip(peak_flops=1e12, hbm_bytes_per_s=1e9, ici_bytes_per_s=1e9)


def compiled_text(fn, *args) -> str:
    return jax.jit(fn).lower(*args).compile().as_text()  # pyright: ignore[reportReturnType] -- as_text() is None only without an HLO module; a compiled program has one


def test_scan_of_matmuls_counts_every_step():
    rng = np.random.default_rng(0)
    n, steps = int(rng.integers(24, 40)), int(rng.integers(5, 12))
    x = jnp.asarray(rng.normal(size=(n, n)), jnp.float32)

    def f(x, w):
        return jax.lax.scan(lambda c, _: (jnp.tanh(c @ w), None), x, None, length=steps)[0]

    est = estimate_hlo(compiled_text(f, x, x), CHIP)
    want = steps * 2.0 * n**3
    assert est.flops == pytest.approx(want, rel=1e-6)
    assert est.loops == 1 and est.unknown_loops == []
    # The loop's work is `steps` times one step's: the same program with one step.
    one = estimate_hlo(compiled_text(lambda x, w: jnp.tanh(x @ w), x, x), CHIP)
    assert one.flops == pytest.approx(2.0 * n**3, rel=1e-6)


def test_elementwise_op_moves_its_operand_and_result():
    rng = np.random.default_rng(1)
    shape = tuple(int(s) for s in rng.integers(8, 64, size=2))
    x = jnp.asarray(rng.normal(size=shape), jnp.float32)
    est = estimate_hlo(compiled_text(lambda x: jnp.exp(x) * 3.0, x), CHIP)
    nbytes = 2 * 4 * math.prod(shape)  # read x, write the result
    assert est.bytes == pytest.approx(nbytes, rel=1e-6)
    assert est.seconds == pytest.approx(nbytes / CHIP.hbm_bytes_per_s, rel=1e-6)
    assert est.flops == 0


def test_matmul_bound_op_costs_flops_over_peak():
    rng = np.random.default_rng(2)
    m, k, n = (int(v) for v in rng.integers(200, 300, size=3))
    a = jnp.asarray(rng.normal(size=(m, k)), jnp.float32)
    b = jnp.asarray(rng.normal(size=(k, n)), jnp.float32)
    chip = Chip(peak_flops=1e9, hbm_bytes_per_s=1e15, ici_bytes_per_s=1e9)  # compute-bound on purpose
    est = estimate_hlo(compiled_text(lambda a, b: a @ b, a, b), chip)
    assert est.seconds == pytest.approx(2.0 * m * k * n / chip.peak_flops, rel=1e-6)
    assert est.matmul_s == pytest.approx(est.seconds)


def test_data_dependent_loop_is_named_and_counted_as_told():
    x = jnp.asarray(np.random.default_rng(3).normal(size=(16, 16)), jnp.float32)

    def f(x):
        return jax.lax.while_loop(lambda c: jnp.sum(c) < 1e6, lambda c: c @ c + 1.0, x)

    text = compiled_text(f, x)
    once, thrice = estimate_hlo(text, CHIP), estimate_hlo(text, CHIP, unknown_trip_count=3)
    assert len(once.unknown_loops) == 1
    assert thrice.flops == pytest.approx(3 * once.flops, rel=1e-6) and once.flops == pytest.approx(2.0 * 16**3)


def test_conditional_costs_its_dearer_branch():
    rng = np.random.default_rng(4)
    n = int(rng.integers(20, 30))
    x = jnp.asarray(rng.normal(size=(n, n)), jnp.float32)

    def f(p, x):
        return jax.lax.cond(p > 0, lambda x: x @ x @ x, lambda x: x + 1.0, x)

    est = estimate_hlo(compiled_text(f, jnp.float32(1.0), x), CHIP)
    assert est.flops == pytest.approx(2 * 2.0 * n**3, rel=1e-6)


def test_parse_module_finds_entry_and_shapes():
    text = compiled_text(lambda x: x * 2.0, jnp.ones((3, 5), jnp.float32))
    comps, entry = parse_module(text)
    assert entry in comps and any(i.opcode == "parameter" for i in comps[entry])
    assert hbm_bytes("(f32[3,5]{1,0}, bf16[7]{0})") == 3 * 5 * 4 + 7 * 2
    assert hbm_bytes("f32[4,4]{1,0:T(8,128)S(1)}") == 0  # on-chip memory moves no HBM bytes


def test_a_loop_reading_one_row_a_step_moves_rows_not_the_array():
    rng = np.random.default_rng(5)
    rows, width = int(rng.integers(40, 60)), 256
    table = jnp.asarray(rng.normal(size=(rows, width)), jnp.float32)

    def f(table):
        def step(acc, i):
            row = jax.lax.dynamic_index_in_dim(table, i, keepdims=False)
            return acc + jnp.tanh(row), None

        return jax.lax.scan(step, jnp.zeros((width,), jnp.float32), jnp.arange(rows))[0]

    est = estimate_hlo(compiled_text(f, table), CHIP)
    full_every_step = rows * rows * width * 4
    # Each step reads one row and the accumulator and writes the accumulator: a few rows'
    # bytes, far below reading the whole table every step.
    assert est.bytes < 0.2 * full_every_step
    assert est.bytes >= rows * width * 4  # every row is read once


def test_a_computation_closed_with_attributes_does_not_swallow_the_next():
    # TPU modules close SparseCore computations with '}, execution_thread="sparsecore"'.
    text = compiled_text(lambda x: x * 2.0, jnp.ones((3, 5), jnp.float32))
    extra = (
        '%offloaded (p: f32[4]) -> f32[4] {\n  ROOT %p = f32[4]{0} parameter(0)\n}, execution_thread="sparsecore"\n\n'
    )
    at = text.index("ENTRY")
    comps, entry = parse_module(text[:at] + extra + text[at:])
    assert "offloaded" in comps and entry in comps and entry != "offloaded"


def test_an_instruction_spanning_lines_stays_in_its_computation():
    # A Pallas kernel's custom call carries metadata with newlines; a continuation line may
    # start with "}}". The instructions after it still belong to the computation.
    text = compiled_text(lambda x: (x * 2.0) @ x.T, jnp.ones((3, 5), jnp.float32))
    at = text.index("ENTRY")
    body = text.index("\n", at) + 1
    extra = '  %kernel = f32[4]{0} custom-call(), custom_call_target="k", frontend_attributes={m={"a":1\n}}, x=1\n'
    comps, entry = parse_module(text[:body] + extra + text[body:])
    names = [i.name for i in comps[entry]]
    assert names[0] == "kernel" and len(names) > 2 and "x=1" in comps[entry][0].attrs
    assert estimate_hlo(text[:body] + extra + text[body:], CHIP).flops == 2 * 3 * 3 * 5
