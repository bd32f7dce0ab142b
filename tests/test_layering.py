"""The package's layering, read from the source with ``ast`` (every import statement,
module-level or inside a function or an ``if``), not from what happens to be imported at
run time:

* no import cycle among ``llrmpp_jax`` modules (a function-level import that closes a
  cycle still is one: it only moves the failure to the call);
* no ``TYPE_CHECKING`` in the package (an import hidden from the interpreter for the type
  checker is how a cycle gets hidden);
* ``llrmpp_jax.data`` reaches nothing of ``experiment``, ``experiment_data``, ``trainer``
  or ``ablation``, directly or through other modules: data knows scenes, sources and
  ``BatchConfig``; the adapters from an experiment to data live in ``experiment_data``.

The oracle for the graph is the file system and Python's own parser; the checks below
first confirm on small made-up packages that they can fail.
"""

from __future__ import annotations

import ast
import os
from collections.abc import Iterator, Mapping

from tests.helpers.environment import ROOT

PACKAGE = "llrmpp_jax"
DATA_MUST_NOT_REACH = (
    "llrmpp_jax.experiment",
    "llrmpp_jax.experiment_data",
    "llrmpp_jax.trainer",
    "llrmpp_jax.ablation",
)


def module_files(root: str, package: str = PACKAGE) -> dict[str, str]:
    """``{dotted module name: file}`` of every ``.py`` under ``root/package``
    (``pkg/__init__.py`` is ``pkg``)."""
    out = {}
    for folder, _, files in os.walk(os.path.join(root, package)):
        for f in files:
            if f.endswith(".py"):
                rel = os.path.relpath(os.path.join(folder, f), root)[:-3].split(os.sep)
                out[".".join(rel[:-1] if rel[-1] == "__init__" else rel)] = os.path.join(folder, f)
    return out


def _resolve(base: str, level: int, importer: str, is_package: bool) -> str:
    """The absolute module of ``from {'.' * level}{base} import ...`` in ``importer``."""
    if level == 0:
        return base
    parts = importer.split(".") if is_package else importer.split(".")[:-1]
    parts = parts[: len(parts) - (level - 1)]
    return ".".join(parts + ([base] if base else []))


def imports_of(tree: ast.AST, importer: str, is_package: bool, modules: Mapping[str, str]) -> set[str]:
    """The package modules a parsed file imports anywhere in it: ``import a.b`` names
    ``a.b``; ``from a import b`` names ``a.b`` when that is a module, else ``a``."""
    found = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            found.update(alias.name for alias in node.names)
        elif isinstance(node, ast.ImportFrom):
            base = _resolve(node.module or "", node.level, importer, is_package)
            for alias in node.names:
                sub = f"{base}.{alias.name}"
                found.add(sub if sub in modules else base)
    return {m for m in found if m in modules and m != importer}


def import_graph(root: str, package: str = PACKAGE) -> dict[str, set[str]]:
    """``{module: the package modules it imports}`` for every module under ``root/package``."""
    modules = module_files(root, package)
    graph = {}
    for name, path in modules.items():
        tree = ast.parse(open(path, encoding="utf-8").read(), path)
        graph[name] = imports_of(tree, name, path.endswith("__init__.py"), modules)
    return graph


def cycles(graph: Mapping[str, set[str]]) -> list[list[str]]:
    """The strongly connected components of more than one module (Tarjan), each sorted."""
    index, low, on_stack, stack, out = {}, {}, set(), [], []

    def visit(v: str) -> None:
        index[v] = low[v] = len(index)
        stack.append(v)
        on_stack.add(v)
        for w in graph.get(v, ()):
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on_stack:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            component = []
            while True:
                w = stack.pop()
                on_stack.discard(w)
                component.append(w)
                if w == v:
                    break
            if len(component) > 1:
                out.append(sorted(component))

    for v in sorted(graph):
        if v not in index:
            visit(v)
    return sorted(out)


def reachable(graph: Mapping[str, set[str]], start: str) -> set[str]:
    """Every module ``start`` imports, directly or through others."""
    seen, todo = set(), [start]
    while todo:
        for w in graph.get(todo.pop(), ()):
            if w not in seen:
                seen.add(w)
                todo.append(w)
    return seen


def type_checking_uses(root: str, package: str = PACKAGE) -> Iterator[str]:
    """``file:line`` of every name or attribute ``TYPE_CHECKING`` under ``root/package``."""
    for path in sorted(module_files(root, package).values()):
        for node in ast.walk(ast.parse(open(path, encoding="utf-8").read(), path)):
            named = (
                (isinstance(node, ast.Name) and node.id == "TYPE_CHECKING")
                or (isinstance(node, ast.Attribute) and node.attr == "TYPE_CHECKING")
                or (isinstance(node, ast.alias) and node.name == "TYPE_CHECKING")
            )
            if named:
                yield f"{os.path.relpath(path, root)}:{getattr(node, 'lineno', '?')}"


def _write(root, files: Mapping[str, str]) -> None:
    for rel, text in files.items():
        path = root / rel
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(text)


def test_the_checks_see_a_cycle_behind_a_function_import_and_type_checking(tmp_path):
    """A made-up package: ``b`` imports ``a`` inside a function (relative), ``a`` imports
    ``b`` at the top, ``c`` hides one under ``TYPE_CHECKING``; ``d`` reaches ``a`` only
    through ``c``'s package re-export."""
    _write(
        tmp_path,
        {
            "pkg/__init__.py": "",
            "pkg/a.py": "from pkg import b\n",
            "pkg/b.py": "def f():\n    from . import a\n    return a\n",
            "pkg/sub/__init__.py": "from pkg.sub.c import C\n",
            "pkg/sub/c.py": "import typing\nif typing.TYPE_CHECKING:\n    from pkg.a import X\nC = 1\n",
            "pkg/d.py": "from pkg.sub import C\n",
        },
    )
    graph = import_graph(str(tmp_path), "pkg")
    assert graph["pkg.b"] == {"pkg.a"} and graph["pkg.a"] == {"pkg.b"}
    assert cycles(graph) == [["pkg.a", "pkg.b"]]
    assert list(type_checking_uses(str(tmp_path), "pkg")) == [os.path.join("pkg", "sub", "c.py") + ":2"]
    assert "pkg.a" in reachable(graph, "pkg.d") and "pkg.d" not in reachable(graph, "pkg.a")


def test_no_import_cycle_in_the_package():
    graph = import_graph(ROOT)
    assert len(graph) > 100 and "llrmpp_jax.data.sources" in graph  # the walk found the package
    assert cycles(graph) == []


def test_no_type_checking_import_in_the_package():
    assert list(type_checking_uses(ROOT)) == []


def test_data_knows_nothing_of_experiments_training_or_ablations():
    graph = import_graph(ROOT)
    data = [m for m in graph if m == "llrmpp_jax.data" or m.startswith("llrmpp_jax.data.")]
    assert "llrmpp_jax.data.held_out" in data
    reached = {m: sorted(w for w in reachable(graph, m) if w.startswith(DATA_MUST_NOT_REACH)) for m in data}
    assert {m: r for m, r in reached.items() if r} == {}
