"""The package's modules import one another without a cycle, counting the imports made inside
functions and under TYPE_CHECKING: a cycle means two modules are one idea split badly, and a
function-level import that hides one only defers the problem to whoever calls it first."""

from __future__ import annotations

import ast
from pathlib import Path

PACKAGE = Path(__file__).resolve().parents[1] / "bayesrob"


def _modules() -> dict[str, Path]:
    out = {}
    for path in PACKAGE.rglob("*.py"):
        parts = path.relative_to(PACKAGE.parent).with_suffix("").parts
        name = ".".join(parts[:-1] if parts[-1] == "__init__" else parts)
        out[name] = path
    return out


def _imports(name: str, path: Path, modules: dict[str, Path]) -> set[str]:
    """The package's modules that ``name`` imports anywhere in its file (a package's own
    parents are left out: importing a submodule runs them first, which is no cycle)."""
    package = name if path.name == "__init__.py" else name.rpartition(".")[0]
    found = set()
    for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
        if isinstance(node, ast.Import):
            targets = [a.name for a in node.names]
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                up = package.split(".")[:len(package.split(".")) - node.level + 1]
                base = ".".join(up + ([base] if base else []))
            targets = [f"{base}.{a.name}" if f"{base}.{a.name}" in modules else base
                       for a in node.names]
        else:
            continue
        for target in targets:
            while target and target not in modules:  # bayesrob.x.y where y is a name in x
                target = target.rpartition(".")[0]
            if target and target != name and not name.startswith(target + "."):
                found.add(target)
    return found


def test_no_module_of_the_package_is_in_an_import_cycle():
    modules = _modules()
    graph = {name: _imports(name, path, modules) for name, path in modules.items()}
    assert len(graph) > 30 and sum(map(len, graph.values())) > 50  # the walk saw the imports
    cycles = []
    for start in graph:
        stack, seen = [(start, (start,))], set()
        while stack:
            node, trail = stack.pop()
            for nxt in graph[node]:
                if nxt == start:
                    cycles.append(" -> ".join((*trail, start)))
                elif nxt not in seen:
                    seen.add(nxt)
                    stack.append((nxt, (*trail, nxt)))
    assert cycles == [], "\n".join(sorted(set(cycles), key=len)[:5])


def test_only_the_reports_lay_out_tables_and_figures():
    """The compute stages return results; their tables and figures are report/'s (and the
    CLI prints them): no module outside bayesrob/report/ and cli.py imports bayesrob.report or
    matplotlib (matplotlib.path's polygon test, geometry, aside)."""
    modules = _modules()
    offenders = []
    for name, path in modules.items():
        if name.startswith("bayesrob.report") or name == "bayesrob.cli":
            continue
        if any(m.startswith("bayesrob.report") for m in _imports(name, path, modules)):
            offenders.append(f"{name} imports bayesrob.report")
        for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
            names = ([a.name for a in node.names] if isinstance(node, ast.Import) else
                     [node.module or ""] if isinstance(node, ast.ImportFrom) else [])
            offenders += [f"{name} imports {n}" for n in names
                          if n.split(".")[0] == "matplotlib" and n != "matplotlib.path"]
    assert len(modules) > 30
    assert offenders == []
