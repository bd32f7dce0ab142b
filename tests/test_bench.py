"""``llrmpp bench``: bad input is one line; the attention benchmark's memory numbers."""

import pytest

from llrmpp_jax.bench import attention_benchmark
from llrmpp_jax.cli import main


@pytest.mark.parametrize(
    "args,message",
    [
        (["bench", "--scale", "huge"], "bench: unknown scale 'huge', expected one of ['cpu', 'paper']"),
        (["bench", "--scale", "cpu", "--only", "scan,attn"], "bench: unknown benchmark(s) ['attn']"),
    ],
)
def test_bench_bad_input_is_one_line(args, message, capsys, tmp_path):
    assert main([*args, "--out", str(tmp_path)]) == 2
    err = capsys.readouterr().err
    assert message in err and err.count("\n") == 1


def test_attention_benchmark_blockwise_memory_is_linear():
    """Compile-only memory analysis at small L: plain attention's temp holds the [nh, L, L]
    logits, blockwise's grows ~linearly (doubling L at most 2.5x its temp)."""
    r = attention_benchmark(lengths=(1024, 2048), run_lengths=(), heads=2, head_dim=16, block=128)
    small, large = r["memory"]
    assert small["xla"]["temp_bytes"] >= small["logits_bytes_per_copy"]
    assert large["blockwise"]["temp_bytes"] < large["logits_bytes_per_copy"] / 4
    assert large["blockwise"]["temp_bytes"] <= 2.5 * small["blockwise"]["temp_bytes"]
