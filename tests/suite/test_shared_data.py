"""``shared_path`` (``tests/helpers/environment.py``): data missing from ``../shared`` skips
a test on a developer's machine, but under ``CI=true`` (where ``../shared`` lies beside the
clone) fails it with one line naming the path -- in a test and at a module's import alike."""

import os
import subprocess
import sys

import pytest

from tests.helpers import environment
from tests.helpers.environment import ROOT, shared_path

MISSING = ("no-such-folder", "no-such-file.npz")
OUTCOMES = (pytest.fail.Exception, pytest.skip.Exception)  # caught both, so a wrong one fails here


def test_missing_shared_data_fails_under_ci(monkeypatch):
    monkeypatch.setenv("CI", "true")
    path = os.path.join(environment.SHARED, *MISSING)
    with pytest.raises(OUTCOMES) as outcome:
        shared_path(*MISSING)
    assert outcome.type is pytest.fail.Exception, outcome
    assert str(outcome.value) == f"CI=true but shared data not found: {path} (clone next to ../shared)"


def test_missing_shared_data_skips_outside_ci(monkeypatch):
    monkeypatch.delenv("CI", raising=False)
    path = os.path.join(environment.SHARED, *MISSING)
    with pytest.raises(OUTCOMES) as outcome:
        shared_path(*MISSING)
    assert outcome.type is pytest.skip.Exception, outcome
    assert str(outcome.value) == f"shared data not found: {path}"


def test_present_shared_data_is_its_path_under_ci(monkeypatch, tmp_path):
    monkeypatch.setattr(environment, "SHARED", str(tmp_path))
    (tmp_path / "golden").mkdir()
    monkeypatch.setenv("CI", "true")
    assert shared_path("golden") == str(tmp_path / "golden")


@pytest.mark.parametrize("ci, outcome", [(None, "1 skipped"), ("true", "1 error")])
def test_a_module_needing_missing_data_is_skipped_or_under_ci_an_error(tmp_path, ci, outcome):
    """A module calling ``shared_path`` at import (as ``capture/test_cli.py`` does), run by
    its own pytest outside the suite: skipped whole without CI, a collection error under it."""
    (tmp_path / "test_needs_shared.py").write_text(
        "from tests.helpers.environment import shared_path\n"
        f"DATA = shared_path(*{MISSING!r})\n\n\ndef test_reads_it():\n    pass\n"
    )
    env = {k: v for k, v in os.environ.items() if k != "CI"}
    env["PYTHONPATH"] = os.pathsep.join([ROOT, *filter(None, [env.get("PYTHONPATH")])])
    if ci is not None:
        env["CI"] = ci
    res = subprocess.run(
        [sys.executable, "-m", "pytest", "-p", "no:cacheprovider", "-q", "-rs", str(tmp_path)],
        cwd=tmp_path,
        env=env,
        capture_output=True,
        text=True,
        timeout=120,
    )
    out = res.stdout + res.stderr
    path = os.path.join(environment.SHARED, *MISSING)
    assert outcome in out.splitlines()[-1], out
    if ci is None:  # the whole module skipped: no test left to run
        assert res.returncode == pytest.ExitCode.NO_TESTS_COLLECTED, out
        assert f"shared data not found: {path}" in out, out
    else:  # a collection error fails the run
        assert res.returncode == pytest.ExitCode.INTERRUPTED, out
        assert f"CI=true but shared data not found: {path} (clone next to ../shared)" in out, out
