"""A temporary git worktree of this checkout at an older commit, for the benchmarks that
compare this tree with it on the same machine in the same run (``bench_splat_baseline.py``,
``bench_decoder_attention.py``), and the checkout's :func:`revision` that the ablation runs
record (``ablation_pilot.py``, ``ablation_probe_depth_scale.py``; ``notebooks/_execute.py``
passes it to the notebooks in ``LLRMPP_NOTEBOOK_REVISION``). Only scripts use git; the
package never does."""

from __future__ import annotations

import contextlib
import os
import subprocess
import tempfile
from collections.abc import Iterator

REPO = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


@contextlib.contextmanager
def worktree(ref: str, repo: str = REPO) -> Iterator[str]:
    """The path of a detached worktree of ``repo`` at ``ref``, removed on exit."""
    with tempfile.TemporaryDirectory() as tmp:
        tree = os.path.join(tmp, "baseline")
        subprocess.run(["git", "-C", repo, "worktree", "add", "--detach", tree, ref], check=True, capture_output=True)
        try:
            yield tree
        finally:
            subprocess.run(["git", "-C", repo, "worktree", "remove", "--force", tree], check=False)


def rev_parse(ref: str, repo: str = REPO) -> str:
    """The full hash ``ref`` names in ``repo`` ('' where git cannot say)."""
    return subprocess.run(["git", "-C", repo, "rev-parse", ref], capture_output=True, text=True).stdout.strip()


def revision(repo: str = REPO) -> str:
    """``repo``'s short commit, with ``+dirty`` when tracked files differ from it
    (``unknown`` where git cannot say)."""

    def git(*args: str) -> str:
        return subprocess.run(["git", "-C", repo, *args], capture_output=True, text=True).stdout.strip()

    head = git("rev-parse", "--short", "HEAD") or "unknown"
    return head + ("+dirty" if git("status", "--porcelain", "--untracked-files=no") else "")
