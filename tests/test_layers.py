"""The layers of ARCHITECTURE.md: imports point down only."""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

import kinreg

PACKAGE = Path(kinreg.__file__).parent

# layer of a module -> the layers it may import (besides its own); the foundation is
# kinreg's top-level modules: errors, geometry, types, config, progress.
ALLOWED = {
    "foundation": set(),
    "io": {"foundation"},
    "estimate": {"foundation", "io"},
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
    """Every kinreg module imported anywhere in the file (also inside functions)."""
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


def test_public_api_resolves() -> None:
    names = [n for n in kinreg.__all__ if n != "__version__"]
    assert set(names) == set(kinreg._API)
    for name in names:
        assert getattr(kinreg, name) is not None
    with pytest.raises(AttributeError):
        _ = kinreg.no_such_name
