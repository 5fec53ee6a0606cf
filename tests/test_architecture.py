"""docs/ARCHITECTURE.md names every module of the packages, so that a newcomer finds each one
by what it does, and the rooms keep their rules (no import cycle inside a package)."""

from __future__ import annotations

import ast
import re
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
PACKAGES = ("cadio", "models", "reports", "flows")


def _modules() -> list[Path]:
    return sorted(p for pkg in PACKAGES for p in (ROOT / pkg).rglob("*.py")
                  if p.name != "__init__.py" and "checkpoints" not in p.parts)


def test_the_architecture_names_every_module() -> None:
    text = (ROOT / "docs" / "ARCHITECTURE.md").read_text()
    named = set(re.findall(r"[A-Za-z_][\w/.]*", text))
    missing = []
    for path in _modules():
        rel = path.relative_to(ROOT)
        room, name = "/".join(rel.parts[:-1]), rel.stem
        # a module is named by its path, its dotted name, or by its stem in its room's line
        dotted = ".".join((*rel.parts[:-1], name))
        line = " ".join(ln for ln in text.splitlines() if ln.startswith(f"{room}/ "))
        if str(rel) not in text and dotted not in named and not re.search(
                rf"\b{re.escape(name)}\b", line):
            missing.append(str(rel))
    assert not missing, f"docs/ARCHITECTURE.md does not name: {missing}"


def _imports(path: Path) -> set[str]:
    out = set()
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            out.add(node.module)
        elif isinstance(node, ast.Import):
            out |= {a.name for a in node.names}
    return out


def _top_level_imports(path: Path) -> set[str]:
    """Modules imported at import time (not inside functions or under TYPE_CHECKING)."""
    out = set()
    for node in ast.parse(path.read_text()).body:
        if isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            out.add(node.module)
        elif isinstance(node, ast.Import):
            out |= {a.name for a in node.names}
    return out


@pytest.mark.parametrize("package", PACKAGES)
def test_no_module_imports_itself_back_at_import_time(package: str) -> None:
    graph, names = {}, _names()
    for path in _modules():
        rel = path.relative_to(ROOT).with_suffix("")
        graph[".".join(rel.parts)] = {m for m in _top_level_imports(path) if m in names}
    cycles = []
    for start in (m for m in graph if m.startswith(package + ".")):
        stack, seen = [(start, [start])], set()
        while stack:
            node, trail = stack.pop()
            for nxt in graph.get(node, ()):
                if nxt == start:
                    cycles.append(" -> ".join([*trail, nxt]))
                elif nxt not in seen:
                    seen.add(nxt)
                    stack.append((nxt, [*trail, nxt]))
    assert not cycles, cycles


def _names() -> set[str]:
    return {".".join(p.relative_to(ROOT).with_suffix("").parts) for p in _modules()}
