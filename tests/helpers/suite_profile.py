"""Where the suite's time goes: with ``LLRMPP_SUITE_PROFILE=DIR``, each pytest process (every
xdist worker) writes ``DIR/<worker>.json`` at the end: per test, its wall seconds (setup, call
and teardown) and the seconds JAX spent in this process tracing to jaxprs, lowering to
StableHLO, and compiling or loading from the persistent cache (JAX's monitoring events), with
the number of programs and of cache hits. What a test's subprocesses (the CLI tests) spend is
in its wall time only. ``experiments/suite_profile.py`` sums the files.

Registered by ``tests/conftest.py``; without the variable it does nothing.
"""

from __future__ import annotations

import json
import os
import threading
import time

import jax.monitoring
import pytest

_EVENTS = {
    "/jax/core/compile/jaxpr_trace_duration": "trace_s",
    "/jax/core/compile/jaxpr_to_mlir_module_duration": "lower_s",
    "/jax/core/compile/backend_compile_duration": "compile_s",
}


class SuiteProfile:
    """The pytest plugin: sums JAX's compile-path durations per test."""

    def __init__(self, out_dir: str) -> None:
        self.out_dir = out_dir
        self.tests: dict[str, dict[str, float]] = {}
        self._current: dict[str, float] | None = None
        self._lock = threading.Lock()
        jax.monitoring.register_event_duration_secs_listener(self._on_duration)
        jax.monitoring.register_event_listener(self._on_event)

    def _add(self, field: str, value: float) -> None:
        with self._lock:
            if self._current is not None:
                self._current[field] = self._current.get(field, 0.0) + value

    def _on_duration(self, event: str, duration_secs: float, **_) -> None:
        field = _EVENTS.get(event)
        if field:
            self._add(field, duration_secs)
            if field == "compile_s":
                self._add("programs", 1)

    def _on_event(self, event: str, **_) -> None:
        if event == "/jax/compilation_cache/cache_hits":
            self._add("hits", 1)

    @pytest.hookimpl(hookwrapper=True)
    def pytest_runtest_protocol(self, item, nextitem):
        record: dict[str, float] = {}
        with self._lock:
            self._current = record
        t0 = time.perf_counter()
        yield
        record["wall_s"] = time.perf_counter() - t0
        with self._lock:
            self._current = None
        self.tests[item.nodeid] = record

    def pytest_sessionfinish(self, session) -> None:
        os.makedirs(self.out_dir, exist_ok=True)
        worker = os.environ.get("PYTEST_XDIST_WORKER", "main")
        with open(os.path.join(self.out_dir, f"{worker}.json"), "w") as f:
            json.dump(self.tests, f, indent=0)


def register(config: pytest.Config) -> None:
    """Install the profile when ``LLRMPP_SUITE_PROFILE`` names a folder."""
    out_dir = os.environ.get("LLRMPP_SUITE_PROFILE")
    if out_dir:
        config.pluginmanager.register(SuiteProfile(out_dir), "llrmpp-suite-profile")
