"""Tests of the test suite's own rules (``tests/helpers``), not of the package."""
