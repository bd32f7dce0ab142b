"""Strict test configuration (equinox-style).

* Two host CPU devices, so multi-device code (pmap, sharding) runs in CI. The flag must be
  in the environment before jax is imported anywhere.
* XLA's CPU backend at optimisation level 0 without its expensive LLVM passes (flags the
  caller sets come after, so they win): most tests run a program once or twice, so compile
  time dominates. The suite takes 774-874 s instead of 948 s on 2 cores (the few tests that run
  long loops, the capture end-to-end ones, get slower); every oracle tolerance still holds.
* ``jax_numpy_dtype_promotion="strict"`` and ``jax_numpy_rank_promotion="raise"``: silent
  float64 upcasts and accidental broadcasting are bugs here.
* x64 is *enabled* so oracles can run in float64; library code must therefore state its
  dtypes explicitly (it does: float32 by default).
* Every function and dataclass of ``llrmpp_jax`` is checked against its annotations
  (jaxtyping's import hook with beartype): array shapes against the letters of
  ``llrmpp_jax.array_typing``'s legend, everything else by type. Functions under ``jit`` are
  checked when traced. The hook only instruments modules imported after it is installed,
  hence before any test module imports the package.
* Compiled programs are dropped after each test module (``jax.clear_caches``). Every live
  XLA:CPU executable holds ~3 memory mappings; an xdist worker that ran half the suite kept
  ~20k of them, reached the kernel's ``vm.max_map_count`` (65,530: its core dump had 65,378
  mappings) and segfaulted inside the next compile. Programs are rarely shared across
  modules, so this costs little compile time.
* What the tests import lives beside this file, not in it: ``tests/helpers`` (``shared_path``,
  ``unchecked``, scenes, toy training) and ``tests/oracles``.
"""

import gc
import os
import sys
import zlib

from tests.helpers.environment import QUICK_XLA_FLAGS

os.environ["XLA_FLAGS"] = " ".join(
    [
        QUICK_XLA_FLAGS,
        os.environ.get("XLA_FLAGS", ""),
        "--xla_force_host_platform_device_count=2",
    ]
)
os.environ.setdefault("JAX_PLATFORMS", "cpu")

import jax  # noqa: E402
import jaxtyping  # noqa: E402
import numpy as np  # noqa: E402
import platformdirs  # noqa: E402
import pytest  # noqa: E402

if "llrmpp_jax" in sys.modules:  # a plugin imported it first: its functions would go unchecked
    raise RuntimeError("llrmpp_jax was imported before tests/conftest.py could install jaxtyping's hook")
# PEP 484's numeric tower (an int where a float is annotated), as static checkers read it.
jaxtyping.install_import_hook("llrmpp_jax", "beartype.beartype(conf=beartype.BeartypeConf(is_pep484_tower=True))")

jax.config.update("jax_enable_x64", True)
jax.config.update("jax_numpy_dtype_promotion", "strict")
jax.config.update("jax_numpy_rank_promotion", "raise")
jax.config.update("jax_default_matmul_precision", "highest")

# The suite's compiled programs persist between runs (JAX's persistent cache: a warm suite
# compiles little). The folder is outside the checkout and its own (the tests' XLA flags differ
# from a user's, so nothing would be shared anyway); in the environment, so the commands the
# tests start in subprocesses use it too. Results must not depend on it: an entry is the same
# executable a fresh compile gives (tests/test_compile_cache.py), and an empty or stale folder
# only costs time.
os.environ.setdefault("JAX_COMPILATION_CACHE_DIR", os.path.join(platformdirs.user_cache_dir("llrmpp_jax"), "xla-tests"))
from llrmpp_jax import compile_cache  # noqa: E402

compile_cache.enable()


@pytest.fixture(autouse=True, scope="module")
def _drop_compiled_programs():
    """Free each module's compiled programs (and their memory mappings) when it ends."""
    yield
    jax.clear_caches()
    gc.collect()


def _seed(request) -> int:
    """Per-test seed from the test's id (crc32: stable across runs, unlike ``hash``), mixed
    with ``LLRMPP_TEST_SEED`` (default 0) so a sweep over fresh draws is one variable away."""
    return zlib.crc32(request.node.nodeid.encode()) ^ int(os.environ.get("LLRMPP_TEST_SEED", "0"))


@pytest.fixture
def key(request) -> jax.Array:
    """A fresh PRNG key per test, derived from the test's id (reproducible, not shared)."""
    return jax.random.key(_seed(request))


@pytest.fixture
def rng(request) -> np.random.Generator:
    """A NumPy generator seeded from the test's id, for oracle-side random data."""
    return np.random.default_rng(_seed(request))


def pytest_configure(config: pytest.Config) -> None:
    """``LLRMPP_SUITE_PROFILE=DIR``: where each test's time goes (``tests/helpers/suite_profile.py``)."""
    from tests.helpers import suite_profile

    suite_profile.register(config)
