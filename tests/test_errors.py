"""The line between a user's mistake and a bug (``llrmpp_jax.errors``, ``cli.main``): a
``UserError`` or an environment fault is one line and exit status 2; anything else keeps its
traceback and exits 1."""

from __future__ import annotations

import os
import subprocess
import sys
import textwrap

import numpy as np
import pytest

from llrmpp_jax.errors import MissingInputError, OutOfSpaceError, UserError

# Runs cli.main with the parser's command replaced by one that raises ``exc``.
_RAISER = textwrap.dedent(
    """
    import errno, sys
    from llrmpp_jax import cli
    from llrmpp_jax.errors import OutOfSpaceError, PeerLostError, UserError

    def fail(args):
        raise {exc}

    build = cli.build_parser

    class Parser:
        def parse_args(self, argv):
            args = build().parse_args(argv)
            args.fn = fail
            return args

    cli.build_parser = Parser
    sys.exit(cli.main(["doctor"]))
    """
)


def _run(code: str, *args: str) -> subprocess.CompletedProcess:
    env = dict(os.environ, JAX_PLATFORMS="cpu")
    return subprocess.run([sys.executable, "-c", code, *args], capture_output=True, text=True, env=env, timeout=300)


def test_error_types_are_what_callers_already_catch():
    assert issubclass(UserError, ValueError)
    assert issubclass(MissingInputError, FileNotFoundError) and issubclass(MissingInputError, UserError)
    assert issubclass(OutOfSpaceError, OSError) and issubclass(OutOfSpaceError, UserError)


@pytest.mark.parametrize(
    "exc, message, status",
    [
        ("UserError('--size: width 0 is not a positive multiple of 16')", "--size: width 0", 2),
        ("PermissionError(errno.EACCES, 'Permission denied', '/root/out')", "Permission denied", 2),
        ("OSError(errno.ENOSPC, 'No space left on device', '/runs/a/ckpt')", "No space left on device", 3),
        ("OSError(errno.EFBIG, 'File too large', '/runs/a/ckpt')", "File too large", 3),
        ("OutOfSpaceError('checkpoint step 3 not saved: /runs/a: quota exceeded')", "quota exceeded", 3),
        ("PeerLostError('lost process 1 of 2: no heartbeat for 20 s')", "lost process 1", 4),
    ],
)
def test_user_and_environment_errors_are_one_line_with_their_status(exc, message, status):
    """Bad input exits 2, out of space 3, a lost peer 4 (so a scheduler can tell them apart)."""
    res = _run(_RAISER.format(exc=exc))
    assert res.returncode == status, res.stderr
    lines = res.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("llrmpp: error:") and message in lines[0], res.stderr


@pytest.mark.parametrize(
    "exc",
    [
        "ValueError('shapes disagree inside the model')",
        "KeyError('params')",
        "OSError(errno.EIO, 'Input/output error')",
    ],
)
def test_internal_errors_keep_their_traceback_exit_1(exc):
    res = _run(_RAISER.format(exc=exc))
    assert res.returncode == 1, res.stderr
    assert "Traceback (most recent call last)" in res.stderr and "llrmpp: error:" not in res.stderr


def test_a_library_check_reaches_the_user_as_one_line(tmp_path):
    """A real command on a file that is not what it claims: the reader's ``UserError``."""
    fake = tmp_path / "scene.gs"
    np.savez(fake, means=np.random.default_rng(0).normal(size=(4, 3)))
    env = dict(os.environ, JAX_PLATFORMS="cpu")
    res = subprocess.run(
        [
            sys.executable,
            "-m",
            "llrmpp_jax.cli",
            "export",
            "--gaussians",
            str(fake),
            "--ply",
            str(tmp_path / "out.ply"),
        ],
        capture_output=True,
        text=True,
        env=env,
        timeout=300,
    )
    assert res.returncode == 2, res.stderr
    lines = res.stderr.strip().splitlines()
    assert len(lines) == 1 and str(fake) in lines[0], res.stderr
    assert not (tmp_path / "out.ply").exists()
