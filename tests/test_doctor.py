"""``llrmpp doctor``: passes on this machine, and fails naming a check that is broken."""

import jax
import pytest

from llrmpp_jax import doctor
from llrmpp_jax.cli import main
from llrmpp_jax.nn import blockwise_attention as BA


@pytest.mark.slow
def test_doctor_passes_here(capsys):
    """Every check within its tolerance on this CPU (about 25 s of CPU time incl. compile)."""
    assert main(["doctor"]) == 0
    out = capsys.readouterr().out
    assert "backend: cpu" in out and "default matmul precision" in out
    for name in doctor.CHECKS:
        assert any(line.startswith("ok") and f" {name} " in line for line in out.splitlines()), name
    assert "all checks passed" in out


def test_doctor_fails_naming_the_broken_check(monkeypatch, capsys):
    """A blockwise kernel that is off by 1e-3 (a TF32-sized error) fails the attention check
    and only it; the slow splat and model checks are left out to keep the test short."""
    real = BA.blockwise_attention
    monkeypatch.setattr(BA, "blockwise_attention", lambda *a, **kw: real(*a, **kw) * 1.001)
    monkeypatch.setattr(doctor, "CHECKS", {n: doctor.CHECKS[n] for n in ("scan", "attention")})
    with jax.default_matmul_precision("default"):  # as a user runs it (the suite runs at 'highest')
        assert main(["doctor"]) == 1
    lines = capsys.readouterr().out.splitlines()
    assert [ln.split()[:2] for ln in lines if ln.startswith(("ok", "FAIL"))] == [["ok", "scan"], ["FAIL", "attention"]]
    assert lines[-1] == "doctor: FAILED: attention"
    assert any("at matmul precision 'highest' too: the kernel is wrong" in ln for ln in lines)


def test_doctor_tells_a_reduced_precision_default_from_a_wrong_kernel(monkeypatch, capsys):
    """A check whose matmuls lose accuracy at the default precision (as TF32 on a GPU: the
    H200 gave 5.8e-4 on the scan) but not at 'highest' fails, and the line under it says
    the kernel is right and how to restore float32."""

    def precision_sensitive() -> float:
        return 1e-7 if jax.config.jax_default_matmul_precision == "highest" else 5.8e-4  # pyright: ignore[reportAttributeAccessIssue] -- jax.config's options are made at run time; its stub lists none

    monkeypatch.setattr(doctor, "CHECKS", {"scan": (precision_sensitive, 1e-4)})
    with jax.default_matmul_precision("default"):  # as a user runs it (the suite runs at 'highest')
        assert main(["doctor"]) == 1
    out = capsys.readouterr().out
    assert "FAIL scan" in out
    assert "scan: error 1.00e-07 at matmul precision 'highest': the kernel is right" in out
    assert "JAX_DEFAULT_MATMUL_PRECISION=highest" in out


def test_doctor_reports_a_crashing_check(monkeypatch, capsys):
    def broken() -> float:
        raise RuntimeError("kernel exploded")

    monkeypatch.setattr(doctor, "CHECKS", {"scan": (broken, 1e-4)})
    assert main(["doctor"]) == 1
    out = capsys.readouterr().out
    assert "scan: raised RuntimeError: kernel exploded" in out and "FAIL scan" in out
