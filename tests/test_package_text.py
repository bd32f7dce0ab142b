"""The package's docstrings and comments say what the code does and why, not its history.

Measurements, sweep tables, commit hashes and dates go stale with every run; they live in
``docs/`` (``docs/lab-notes.md``: the dated history; ``docs/results.md``,
``docs/speed-cpu.md``: the current numbers with the command that makes each). The package
links there at most (``docs/lab-notes.md`` as a path is allowed; "lab notes" as a citation
is not), and it never runs git: a wheel is no checkout.

Every ``.py`` file under ``llrmpp_jax/`` is read twice: its docstrings (every string
expression statement) and comments (``tokenize``) against the text patterns below, and its
code (``ast``) for a git invocation (a string constant ``"git"`` or ``"git ..."``). A
failure lists ``file:line: rule: the line``.
"""

import ast
import io
import os
import re
import tokenize

import pytest

import llrmpp_jax

PACKAGE = os.path.dirname(os.path.abspath(llrmpp_jax.__file__))

# (rule, pattern) on one line of a docstring or comment.
TEXT_RULES = [
    # 7-40 lowercase hex digits with at least one letter and one digit, alone: a commit's
    # short or full hash ("dce295e"), not a number ("1048576") or a word ("defaced").
    (
        "commit hash",
        re.compile(
            r"(?<![0-9A-Za-z_])(?=[0-9a-f]*[a-f])(?=[0-9a-f]*[0-9])[0-9a-f]{7,40}"
            r"(?![0-9A-Za-z_])"
        ),
    ),
    ("date", re.compile(r"20\d\d-\d\d-\d\d")),
    ("table row", re.compile(r"^\s*\|")),
    # "lab notes" / "lab-notes" as a citation; the path docs/lab-notes.md is a link.
    ("lab notes", re.compile(r"(?<!docs/)lab[- ]notes?(?!\.md)", re.IGNORECASE)),
    ("experiments/results", re.compile(r"experiments/results")),
    ("git", re.compile(r"(?<![\w./-])git(?![\w-])")),
]


def _python_files() -> list[str]:
    out = []
    for root, _, files in os.walk(PACKAGE):
        out += [os.path.join(root, f) for f in sorted(files) if f.endswith(".py")]
    return sorted(out)


def _text_lines(source: str) -> list[tuple[int, str]]:
    """(line number, text) of every docstring line (string expression statements: module,
    class and function docstrings and bare strings) and every comment."""
    lines = []
    for node in ast.walk(ast.parse(source)):
        if isinstance(node, ast.Expr) and isinstance(node.value, ast.Constant) and isinstance(node.value.value, str):
            lines += [(node.lineno + i, text) for i, text in enumerate(node.value.value.splitlines())]
    for tok in tokenize.generate_tokens(io.StringIO(source).readline):
        if tok.type == tokenize.COMMENT:
            lines.append((tok.start[0], tok.string.lstrip("#")))
    return lines


def _git_calls(source: str) -> list[int]:
    """Lines of code (not docstrings) with a string constant that runs git: ``"git"`` as an
    argv's first word or ``"git ..."`` as a shell command."""
    tree = ast.parse(source)
    docs = {id(n.value) for n in ast.walk(tree) if isinstance(n, ast.Expr) and isinstance(n.value, ast.Constant)}
    return sorted(
        n.lineno
        for n in ast.walk(tree)
        if isinstance(n, ast.Constant)
        and isinstance(n.value, str)
        and id(n) not in docs
        and (n.value == "git" or n.value.startswith("git "))
    )


def package_findings() -> list[str]:
    """``file:line: rule: text`` for every line of the package that breaks a rule."""
    found = []
    for path in _python_files():
        rel = os.path.relpath(path, os.path.dirname(PACKAGE))
        source = open(path, encoding="utf-8").read()
        for lineno, text in sorted(_text_lines(source)):
            for rule, pattern in TEXT_RULES:
                if pattern.search(text):
                    found.append(f"{rel}:{lineno}: {rule}: {text.strip()}")
        found += [f"{rel}:{lineno}: git call" for lineno in _git_calls(source)]
    return found


def test_no_history_measurements_or_git_in_the_package():
    found = package_findings()
    assert not found, f"{len(found)} lines of llrmpp_jax/ carry history or run git:\n" + "\n".join(found)


@pytest.mark.parametrize(
    "text, rule",
    [
        ("the old kernel (dce295e) was slower", "commit hash"),
        ("see 3b68f44a9c for the sweep", "commit hash"),
        ("shipped until 2026-11-26", "date"),
        ("| step | PSNR |", "table row"),
        ("  |---|---|", "table row"),
        ("measured in the lab notes, round 3", "lab notes"),
        ("(lab-notes section 4)", "lab notes"),
        ("see experiments/results/splat_speed.json", "experiments/results"),
        ("in git history at that commit", "git"),
        ("subprocess.run(['git', 'rev-parse'])", "git"),
    ],
)
def test_each_rule_catches_its_kind_of_line(text, rule):
    hits = [name for name, pattern in TEXT_RULES if pattern.search(text)]
    assert rule in hits, (text, hits)


@pytest.mark.parametrize(
    "text",
    [
        "the learning rate is 1e-3 because 2e-3 stalls seeds; see docs/lab-notes.md",
        "see docs/lab-notes.md#refinement-rates and docs/results.md",
        "a [B, 1048576] buffer of float32 values, logit(opacity), 0x7f800000",
        "the defaced digit; legit digits; a decade",
    ],
)
def test_behavioural_text_passes(text):
    hits = [name for name, pattern in TEXT_RULES if pattern.search(text)]
    assert not hits, (text, hits)


def test_a_git_call_in_code_is_found_and_a_docstring_is_not_code():
    source = (
        '"""git is named here only in text."""\n'
        "import subprocess\n"
        'subprocess.run(["git", "-C", ".", "status"])\n'
        'os.system("git worktree add t HEAD")\n'
        'subprocess.run(["python", "-c", "pass"])\n'
    )
    assert _git_calls(source) == [3, 4]
    assert [n for n, _ in _text_lines(source)] == [1]
