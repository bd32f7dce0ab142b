"""Switching off the suite's annotation checks (installed by ``tests/conftest.py``) for a block."""

import contextlib

import jaxtyping


@contextlib.contextmanager
def unchecked():
    """The annotation checks off inside the block: for a test that passes what the
    annotations rule out on purpose, to reach the library's own error for it (what a user
    sees: nothing is checked outside the tests)."""
    before = jaxtyping.config.jaxtyping_disable
    jaxtyping.config.update("jaxtyping_disable", True)
    try:
        yield
    finally:
        jaxtyping.config.update("jaxtyping_disable", before)
