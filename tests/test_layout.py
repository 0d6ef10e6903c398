"""The shape of the ``jtraj`` package, read from its source with ``ast`` (nothing is
imported or compiled, so this file is cheap):

* no import cycle between jtraj's modules (imports inside functions count: they are
  dependencies all the same);
* dependencies point one way: the library never imports the command line
  (``jtraj.cli``, ``jtraj.commands``);
* no module imports a private name (``from .x import _y``) of another module, nor
  reaches one through an imported module (``x._y``); :mod:`jtraj._testing`, the
  explicitly internal surface for tests and benchmarks, is the one module allowed to;
* the generic ANFIS (``jtraj.anfis``) knows nothing of trajectories: it imports no
  dataset, solver, planner or robot module (:mod:`jtraj.mappings` builds trajectory
  models on top of it);
* no module over 800 lines.
"""

from __future__ import annotations

import ast
import pathlib

import pytest

ROOT = pathlib.Path(__file__).resolve().parents[1] / "jtraj"
MAX_LINES = 800
CLI = ("jtraj.cli", "jtraj.commands")
TESTING = "jtraj._testing"


def _modules(root: pathlib.Path = ROOT) -> dict[str, tuple[pathlib.Path, bool]]:
    """``{dotted name: (path, is_package)}`` for every ``.py`` file under ``root``."""
    out = {}
    for path in sorted(root.rglob("*.py")):
        parts = list(path.relative_to(root.parent).with_suffix("").parts)
        package = parts[-1] == "__init__"
        if package:
            parts = parts[:-1]
        out[".".join(parts)] = (path, package)
    return out


def _absolute(module: str | None, level: int, importer: str, package: bool) -> str:
    if level == 0:
        return module or ""
    base = importer.split(".") if package else importer.split(".")[:-1]
    base = base[:len(base) - (level - 1)]
    return ".".join(base + ([module] if module else []))


def _scan(modules):
    """(edges, private uses): ``edges[m]`` is the set of jtraj modules ``m`` imports;
    private uses are ``(importer, module, name)``."""
    edges: dict[str, set[str]] = {m: set() for m in modules}
    private: set[tuple[str, str, str]] = set()
    for name, (path, package) in modules.items():
        tree = ast.parse(path.read_text(), filename=str(path))
        aliases: dict[str, str] = {}  # local name -> jtraj module it is bound to
        for node in ast.walk(tree):
            if isinstance(node, ast.ImportFrom):
                target = _absolute(node.module, node.level, name, package)
                if target != "jtraj" and not target.startswith("jtraj."):
                    continue
                for alias in node.names:
                    full = f"{target}.{alias.name}"
                    if full in modules:  # a submodule
                        edges[name].add(full)
                        aliases[alias.asname or alias.name] = full
                        continue
                    edges[name].add(target)
                    if alias.name.startswith("_") and not alias.name.startswith("__"):
                        private.add((name, target, alias.name))
            elif isinstance(node, ast.Import):
                for alias in node.names:
                    if alias.name == "jtraj" or alias.name.startswith("jtraj."):
                        edges[name].add(alias.name)
                        if alias.asname:
                            aliases[alias.asname] = alias.name
        for node in ast.walk(tree):
            if (isinstance(node, ast.Attribute) and isinstance(node.value, ast.Name) and node.value.id in aliases
                    and node.attr.startswith("_") and not node.attr.startswith("__")):
                private.add((name, aliases[node.value.id], node.attr))
    for name in edges:
        edges[name].discard(name)
    return edges, private


def _cycles(edges: dict[str, set[str]]) -> list[list[str]]:
    """The strongly connected components with more than one module (Tarjan)."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on: set[str] = set()
    out: list[list[str]] = []

    def visit(v):
        index[v] = low[v] = len(index)
        stack.append(v)
        on.add(v)
        for w in edges.get(v, ()):
            if w not in edges:
                continue
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            comp = []
            while True:
                w = stack.pop()
                on.discard(w)
                comp.append(w)
                if w == v:
                    break
            if len(comp) > 1:
                out.append(sorted(comp))

    for v in sorted(edges):
        if v not in index:
            visit(v)
    return out


@pytest.fixture(scope="module")
def graph():
    modules = _modules()
    edges, private = _scan(modules)
    return modules, edges, private


def test_no_import_cycle(graph):
    _, edges, _ = graph
    cycles = sorted(_cycles(edges))
    assert cycles == []


def test_the_library_never_imports_the_command_line(graph):
    _, edges, _ = graph
    upward = sorted((m, t) for m, ts in edges.items() if not m.startswith(CLI)
                    for t in ts if t.startswith(CLI))
    assert upward == []


def test_the_anfis_is_generic(graph):
    _, edges, _ = graph
    generic = {t for m, ts in edges.items() if m.startswith("jtraj.anfis") for t in ts}
    assert sorted(t for t in generic if not t.startswith("jtraj.anfis")) == []


def test_no_private_name_crosses_modules(graph):
    _, _, private = graph
    crossing = {p for p in private if p[0] != TESTING}
    assert sorted(crossing) == [], "import a public name (or go through jtraj._testing in tests)"


def test_no_module_over_800_lines(graph):
    modules, _, _ = graph
    long = sorted((m, n) for m, (p, _) in modules.items() if (n := len(p.read_text().splitlines())) > MAX_LINES)
    assert long == []


def test_the_checks_see_what_they_look_for(tmp_path):
    """The scanner on a small package of its own: a cycle, an upward import, a private
    import and a private attribute are all found."""
    pkg = tmp_path / "jtraj"
    (pkg / "commands").mkdir(parents=True)
    (pkg / "__init__.py").write_text("from . import a\n")
    (pkg / "a.py").write_text("from .b import _hidden\n")
    (pkg / "b.py").write_text("def f():\n    from . import a\n    from jtraj import c\n    return c._secret\n")
    (pkg / "c.py").write_text("from jtraj.commands import run\n")
    (pkg / "commands" / "__init__.py").write_text("def run(): pass\n")
    (pkg / "commands" / "go.py").write_text("from jtraj import a\n")  # downward: allowed
    modules = _modules(pkg)
    edges, private = _scan(modules)
    assert _cycles(edges) == [["jtraj.a", "jtraj.b"]]
    assert ("jtraj.a", "jtraj.b", "_hidden") in private and ("jtraj.b", "jtraj.c", "_secret") in private
    upward = [(m, t) for m, ts in edges.items() if not m.startswith(CLI) for t in ts if t.startswith(CLI)]
    assert upward == [("jtraj.c", "jtraj.commands")]
