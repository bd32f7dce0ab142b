"""The test suite, laid out like the package: the tests of ``llrmpp_jax/<sub>/<module>.py``
are ``tests/<sub>/test_<module>.py``, those of a top-level module ``tests/test_<module>.py``.

Oracles and helpers that more than one test module uses live in ``tests/oracles`` and
``tests/helpers``; a test module imports from those, never from another test module. Every
folder is a package, so two test modules may share a file name in different folders
(``tests.test_cli`` and ``tests.capture.test_cli``) and ``tests/conftest.py`` applies to all.
"""
