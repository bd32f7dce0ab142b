"""The suite's environment: XLA's quick CPU flags, the checkout's root and the ``../shared``
folder beside it.

Imports nothing but ``os`` and ``pytest``: ``tests/conftest.py`` reads :data:`QUICK_XLA_FLAGS`
from here before jax is imported.
"""

import os

import pytest

QUICK_XLA_FLAGS = "--xla_backend_optimization_level=0 --xla_llvm_disable_expensive_passes=true"

ROOT = os.path.abspath(os.path.join(os.path.dirname(__file__), "..", ".."))  # the checkout
SHARED = os.path.abspath(os.path.join(ROOT, "..", "shared"))
GOLDEN = os.path.join(SHARED, "golden", "long_lrm_tiny")


def shared_path(*parts: str) -> str:
    """Path inside ``../shared``; skips the test (or, called at import, the module) if the
    folder is absent -- except under ``CI=true``, where that fails the test."""
    p = os.path.join(SHARED, *parts)
    if not os.path.exists(p):
        if os.environ.get("CI"):  # CI has ../shared beside the clone: its absence is a failure
            pytest.fail(f"CI=true but shared data not found: {p} (clone next to ../shared)", pytrace=False)
        pytest.skip(f"shared data not found: {p}", allow_module_level=True)
    return p
