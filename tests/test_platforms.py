"""A command on a machine with libtpu but no TPU starts no TPU plugin (and prints nothing of it)."""

import os
import subprocess
import sys

import pytest

from llrmpp_jax.platforms import has_tpu_device

PROBE = "from llrmpp_jax.platforms import skip_absent_tpu; skip_absent_tpu(); import jax; print(jax.default_backend())"


@pytest.mark.skipif(has_tpu_device(), reason="this host has a TPU")
def test_without_a_tpu_the_tpu_plugin_is_not_started():
    pytest.importorskip("libtpu")
    env = {k: v for k, v in os.environ.items() if k != "JAX_PLATFORMS"}
    done = subprocess.run([sys.executable, "-c", PROBE], capture_output=True, text=True, env=env, timeout=120)
    assert done.returncode == 0, done.stderr
    assert done.stdout.strip() == "cpu"
    assert "TPU" not in done.stderr, done.stderr
    # The oracle that the probe means something: without the call, the plugin starts and warns.
    bare = subprocess.run(
        [sys.executable, "-c", "import jax; jax.devices()"], capture_output=True, text=True, env=env, timeout=120
    )
    assert "TPU" in bare.stderr


def test_a_platform_the_user_chose_is_kept():
    env = {**os.environ, "JAX_PLATFORMS": "tpu,cpu"}  # would read "cpu" had the call overridden it
    probe = (
        "import jax; from llrmpp_jax.platforms import skip_absent_tpu; skip_absent_tpu(); "
        "print(jax.config.jax_platforms)"
    )
    done = subprocess.run([sys.executable, "-c", probe], capture_output=True, text=True, env=env, timeout=120)
    assert done.stdout.strip() == "tpu,cpu", done.stderr
