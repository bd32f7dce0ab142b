"""The workdir lock: one train per workdir, the holder named, no stale lock after SIGKILL."""

import os
import re
import signal
import subprocess
import sys
import time

import pytest

from llrmpp_jax.train.workdir_lock import LOCK_NAME, WorkdirBusyError, workdir_lock
from tests.helpers.environment import ROOT

HOLD = """
import sys, time
from llrmpp_jax.train.workdir_lock import workdir_lock
with workdir_lock(sys.argv[1]):
    print("held", flush=True)
    time.sleep(120)
"""


def _holder(workdir):
    proc = subprocess.Popen([sys.executable, "-c", HOLD, workdir], stdout=subprocess.PIPE, text=True)
    assert proc.stdout.readline().strip() == "held"  # pyright: ignore[reportOptionalMemberAccess] -- Popen(..., stdout/stderr=PIPE): the stream is set
    return proc


def test_second_holder_is_refused_naming_the_first_and_a_killed_holder_leaves_no_lock(tmp_path):
    work = str(tmp_path / "w")
    proc = _holder(work)
    try:
        with pytest.raises(WorkdirBusyError) as err, workdir_lock(work):
            pass
        assert f"(pid {proc.pid} on " in str(err.value) and len(str(err.value).splitlines()) == 1
    finally:
        proc.send_signal(signal.SIGKILL)
        proc.wait()
    assert os.path.exists(os.path.join(work, LOCK_NAME))  # the file stays, its lock does not
    with workdir_lock(work) as path:
        assert re.fullmatch(rf"pid {os.getpid()} on \S+\n", open(path).read())
    with workdir_lock(work):  # released on exit from the block
        pass


def test_llrmpp_train_on_a_busy_workdir_is_one_line(tmp_path):
    work = str(tmp_path / "w")
    proc = _holder(work)
    try:
        t0 = time.time()
        res = subprocess.run(
            [sys.executable, "-m", "llrmpp_jax.cli", "train", "--config", "demo", "--workdir", work],
            capture_output=True,
            text=True,
            timeout=300,
            cwd=ROOT,
        )
    finally:
        proc.send_signal(signal.SIGKILL)
        proc.wait()
    assert res.returncode == 2, res.stderr
    assert res.stderr.strip().splitlines() == [
        f"llrmpp: error: {work}: another llrmpp train is using this workdir (pid {proc.pid} on "
        f"{os.uname().nodename}); wait for it to finish or stop it, or train in another --workdir"
    ]
    assert time.time() - t0 < 120  # refused at the door, before any compile
