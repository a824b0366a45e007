"""The layers of ARCHITECTURE.md: imports point down only, no module imports the package itself,
and no two modules import each other (directly or round a circle)."""

from __future__ import annotations

import ast
from collections.abc import Mapping
from pathlib import Path

import pytest

import kinreg

PACKAGE = Path(kinreg.__file__).parent

# layer of a module -> the layers it may import (besides its own); the foundation is
# kinreg's top-level modules: errors, geometry, types, survey, config, progress, _version.
ALLOWED = {
    "foundation": set(),
    "io": {"foundation"},
    "estimate": {"foundation"},
    "calibration": {"foundation", "io"},
    "simulation": {"foundation", "io"},
    "report": {"foundation", "io", "estimate"},
    "run": {"foundation", "io", "estimate", "report"},
}


def _layer(module: str) -> str:
    parts = module.split(".")
    if len(parts) >= 3 or (len(parts) == 2 and (PACKAGE / parts[1]).is_dir()):
        return parts[1]
    return "foundation"


def _imports(path: Path) -> list[tuple[int, str]]:
    """Every kinreg module imported anywhere in the file (also inside functions and under
    ``TYPE_CHECKING``); ``from kinreg import x`` counts as ``kinreg.x``."""
    found = []
    for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
        if isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
            names = [node.module] if node.module != "kinreg" else [f"kinreg.{a.name}" for a in node.names]
            found += [(node.lineno, name) for name in names]
        elif isinstance(node, ast.Import):
            found += [(node.lineno, a.name) for a in node.names]
    return [(line, name) for line, name in found if name == "kinreg" or name.startswith("kinreg.")]


def _module(path: Path) -> str:
    parts = path.relative_to(PACKAGE.parent).with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


MODULES = sorted(p for p in PACKAGE.rglob("*.py") if p.name != "__init__.py" or p.parent != PACKAGE)


def _upward_imports(path: Path, module: str) -> list[str]:
    layer = _layer(module)
    return [f"line {line}: {name} ({_layer(name)})" for line, name in _imports(path)
            if name != "kinreg" and _layer(name) not in ALLOWED[layer] | {layer}]


@pytest.mark.parametrize("path", MODULES, ids=lambda p: str(p.relative_to(PACKAGE)))
def test_imports_point_down(path: Path) -> None:
    wrong = _upward_imports(path, _module(path))
    assert not wrong, f"{_module(path)} imports upwards: {wrong}"


def test_the_rule_catches_an_upward_import(tmp_path: Path) -> None:
    probe = tmp_path / "probe.py"
    probe.write_text("def f():\n    from kinreg.run.pipeline import process\n", encoding="utf-8")
    assert _upward_imports(probe, "kinreg.estimate.probe") == ["line 2: kinreg.run.pipeline (run)"]
    assert _upward_imports(probe, "kinreg.run.probe") == []
    probe.write_text("from kinreg.io.control import ControlPoints\n", encoding="utf-8")
    assert _upward_imports(probe, "kinreg.estimate.probe") == ["line 1: kinreg.io.control (io)"]
    assert _upward_imports(probe, "kinreg.report.probe") == []


# --------------------------------------------------------------------------- the package itself


def _package_imports(path: Path) -> list[str]:
    """Where a file imports the package ``kinreg`` itself (``import kinreg``, ``from kinreg import
    x``) rather than one of its modules by name: inside the package that runs ``__init__``'s
    imports from within a module they may be importing, and reaches round the layers."""
    found = []
    for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
        if isinstance(node, ast.ImportFrom) and node.level == 0 and node.module == "kinreg":
            found.append(f"line {node.lineno}: from kinreg import {', '.join(a.name for a in node.names)}")
        elif isinstance(node, ast.Import):
            found += [f"line {node.lineno}: import kinreg" for a in node.names if a.name == "kinreg"]
    return found


@pytest.mark.parametrize("path", MODULES, ids=lambda p: str(p.relative_to(PACKAGE)))
def test_no_module_imports_the_package_itself(path: Path) -> None:
    found = _package_imports(path)
    assert not found, f"{_module(path)} imports the package kinreg: {found}"


def test_the_rule_catches_a_package_import(tmp_path: Path) -> None:
    probe = tmp_path / "probe.py"
    probe.write_text("import kinreg\n\ndef f():\n    from kinreg import __version__\n", encoding="utf-8")
    assert _package_imports(probe) == ["line 1: import kinreg", "line 4: from kinreg import __version__"]
    probe.write_text("import kinreg.io.las\nfrom kinreg._version import __version__\n", encoding="utf-8")
    assert _package_imports(probe) == []


# --------------------------------------------------------------------------- circles


def _import_graph(modules: Mapping[str, Path]) -> dict[str, set[str]]:
    """Per module the modules of ``modules`` it imports anywhere (also inside functions and under
    ``TYPE_CHECKING``): ``from kinreg.a.b import c`` is ``kinreg.a.b.c`` where that is a module,
    else ``kinreg.a.b``."""
    def resolve(name: str) -> str:
        while name and name not in modules:
            name = name.rpartition(".")[0]
        return name

    graph = {}
    for module, path in modules.items():
        imported = set()
        for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
            if isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
                imported |= {resolve(f"{node.module}.{a.name}") for a in node.names}
            elif isinstance(node, ast.Import):
                imported |= {resolve(a.name) for a in node.names}
        graph[module] = imported - {"", module}
    return graph


def _circles(graph: Mapping[str, set[str]]) -> list[list[str]]:
    """The modules that import each other, directly or round a circle: the strongly connected
    components of more than one module (Tarjan's algorithm, without recursion), each sorted."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    found = []
    for root in sorted(graph):
        if root in index:
            continue
        work = [(root, iter(sorted(graph[root])))]
        index[root] = low[root] = len(index)
        stack.append(root)
        on_stack.add(root)
        while work:
            node, edges = work[-1]
            for nxt in edges:
                if nxt not in index:
                    index[nxt] = low[nxt] = len(index)
                    stack.append(nxt)
                    on_stack.add(nxt)
                    work.append((nxt, iter(sorted(graph.get(nxt, ())))))
                    break
                if nxt in on_stack:
                    low[node] = min(low[node], index[nxt])
            else:
                work.pop()
                if work:
                    low[work[-1][0]] = min(low[work[-1][0]], low[node])
                if low[node] == index[node]:
                    component = []
                    while True:
                        member = stack.pop()
                        on_stack.discard(member)
                        component.append(member)
                        if member == node:
                            break
                    if len(component) > 1:
                        found.append(sorted(component))
    return sorted(found)


def test_no_import_circles() -> None:
    modules = {_module(p): p for p in PACKAGE.rglob("*.py")}
    circles = _circles(_import_graph(modules))
    assert not circles, f"modules that import each other: {circles}"


def test_the_rule_catches_an_import_circle(tmp_path: Path) -> None:
    for name, text in {"a": "def f():\n    from kinreg.probe.b import g\n",
                       "b": "from kinreg.probe import c\n",
                       "c": "from typing import TYPE_CHECKING\nif TYPE_CHECKING:\n    import kinreg.probe.a\n",
                       "d": "from kinreg.probe.a import f\n"}.items():
        (tmp_path / f"{name}.py").write_text(text, encoding="utf-8")
    modules = {f"kinreg.probe.{p.stem}": p for p in tmp_path.glob("*.py")}
    assert _circles(_import_graph(modules)) == [["kinreg.probe.a", "kinreg.probe.b", "kinreg.probe.c"]]
    (tmp_path / "c.py").write_text("import numpy\n", encoding="utf-8")
    assert _circles(_import_graph(modules)) == []


def test_public_api_resolves() -> None:
    names = [n for n in kinreg.__all__ if n != "__version__"]
    assert set(names) == set(kinreg._API)
    for name in names:
        assert getattr(kinreg, name) is not None
    with pytest.raises(AttributeError):
        _ = kinreg.no_such_name
    from kinreg._version import __version__

    assert kinreg.__version__ == __version__
