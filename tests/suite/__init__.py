"""Tests of the test suite's own rules (``tests/helpers``) and of the repository's (the index of
``experiments/results/``), not of the package."""
