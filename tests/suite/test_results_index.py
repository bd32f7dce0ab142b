"""``experiments/results/README.md`` indexes the folder: each table row's first cell holds
patterns in backticks, relative to ``experiments/results/`` (``*``, ``{a,b}``; one ending in
``/`` is a whole folder). Every tracked file there is covered by a pattern, and every pattern
covers a file, so a result nothing cites cannot stay in the tree unnoticed, nor an index row
outlive its file."""

import fnmatch
import os
import re
import subprocess

import pytest

from tests.helpers.environment import ROOT

RESULTS = os.path.join(ROOT, "experiments", "results")
INDEX = "README.md"  # the index itself, relative to RESULTS


def expand_braces(pattern: str) -> list[str]:
    """``a{b,c}d{e,f}`` -> ``abde``, ``abdf``, ``acde``, ``acdf`` (braces do not nest)."""
    brace = re.search(r"\{([^{}]*)\}", pattern)
    if brace is None:
        return [pattern]
    head, tail = pattern[: brace.start()], pattern[brace.end() :]
    return [p for alt in brace.group(1).split(",") for p in expand_braces(head + alt + tail)]


def index_patterns(text: str) -> list[str]:
    """The backticked patterns in the first cell of every table row of ``text``."""
    patterns = []
    for line in text.splitlines():
        if line.startswith("|"):
            patterns += re.findall(r"`([^`]+)`", line.split("|")[1])
    return patterns


def covers(pattern: str, path: str) -> bool:
    if pattern.endswith("/"):
        return path.startswith(pattern)
    return any(fnmatch.fnmatchcase(path, p) for p in expand_braces(pattern))


def unindexed(files: list[str], patterns: list[str]) -> list[str]:
    return [f for f in files if f != INDEX and not any(covers(p, f) for p in patterns)]


def unmatched(patterns: list[str], files: list[str]) -> list[str]:
    return [p for p in patterns if not any(covers(p, f) for f in files)]


def result_files() -> list[str]:
    """The files under ``experiments/results/`` relative to it: git's tracked ones in a
    checkout, else what is on disk (an unpacked source tree)."""
    try:
        res = subprocess.run(
            ["git", "ls-files", "-z", "--", "."], cwd=RESULTS, capture_output=True, text=True, timeout=60
        )
        if res.returncode == 0:
            return sorted(filter(None, res.stdout.split("\0")))
    except (FileNotFoundError, NotADirectoryError):  # no git, or no folder
        pass
    if not os.path.isdir(RESULTS):
        pytest.skip(f"neither a git checkout nor a folder {RESULTS} to list")
    return sorted(
        os.path.relpath(os.path.join(d, f), RESULTS).replace(os.sep, "/")
        for d, _, names in os.walk(RESULTS)
        for f in names
    )


@pytest.fixture(scope="module")
def files() -> list[str]:
    return result_files()


@pytest.fixture(scope="module")
def patterns() -> list[str]:
    with open(os.path.join(RESULTS, INDEX)) as f:
        return index_patterns(f.read())


def test_every_result_file_is_indexed(files: list[str], patterns: list[str]):
    assert INDEX in files
    missing = unindexed(files, patterns)
    assert not missing, f"not in experiments/results/README.md (cite it or remove it): {missing}"


def test_every_index_entry_matches_a_file(files: list[str], patterns: list[str]):
    assert patterns
    stale = unmatched(patterns, files)
    assert not stale, f"experiments/results/README.md lists what is not there: {stale}"


def test_brace_patterns_and_folders():
    assert expand_braces("t{4,5}_*.{json,png}") == ["t4_*.json", "t4_*.png", "t5_*.json", "t5_*.png"]
    assert expand_braces("a_{,2}.json") == ["a_.json", "a_2.json"]
    row = "| `a/{x,y}.json`, `b/` | made by `c.py` | cited in `d.md` |"
    assert index_patterns(f"| files | by | in |\n|---|---|---|\n{row}\n`e.json` outside a table") == [
        "a/{x,y}.json",
        "b/",
    ]
    files = ["README.md", "a/x.json", "a/y.json", "b/c/d.txt", "z.json"]
    assert unindexed(files, ["a/{x,y}.json", "b/"]) == ["z.json"]
    assert unmatched(["a/{x,y}.json", "b/", "a/w*.json", "c/"], files) == ["a/w*.json", "c/"]
