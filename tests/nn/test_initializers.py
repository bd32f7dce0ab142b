"""``init_std`` of the Gaussian head and the decoder (``nn/initializers.py``): Long-LRM's
N(0, 0.02) by default, LeCun normal (std 1/sqrt(fan-in)) with None. Oracle: the sample std
of the initialised kernels against the stated std (thousands of draws, so +-10% is more than
5 sigma; the decoder's merge kernel, 64 weights, is too small to test this way)."""

from dataclasses import replace

import jax
import numpy as np
import pytest

from llrmpp_jax import config as C
from llrmpp_jax.model import init_params


def _kernels(params: dict) -> dict[str, np.ndarray]:
    dec = params["decoder"]
    return {
        "head": params["head"]["proj"]["kernel"],
        "tokenizer": dec["tokenizer"]["kernel"],
        "head_rgb": dec["head_rgb"]["kernel"],
    }


@pytest.mark.parametrize("std", [0.02, None])
def test_head_and_decoder_kernels_have_the_configured_std(std):
    cfg = C.tiny()
    cfg = replace(cfg, head=replace(cfg.head, init_std=std), decoder=replace(cfg.decoder, init_std=std))
    params = init_params(jax.random.key(3), cfg, 2, 64, 64)
    for name, k in _kernels(params).items():
        k = np.asarray(k, np.float64)
        want = std if std is not None else 1.0 / np.sqrt(k.shape[0])
        assert abs(k.std() / want - 1) < 0.1, (name, k.shape, k.std(), want)
        assert abs(k.mean()) < 0.1 * want, name
    # The backbone keeps Long-LRM's N(0, 0.02) either way.
    qkv = np.asarray(params["backbone"]["blocks_0"]["attn"]["qkv"]["kernel"], np.float64)
    assert abs(qkv.std() / 0.02 - 1) < 0.1
