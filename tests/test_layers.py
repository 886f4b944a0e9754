"""The package graph is one-way: walk every module's imports and check the layering rules."""

from __future__ import annotations

import ast
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def _imports(path: Path) -> set[str]:
    tree = ast.parse(path.read_text(encoding="utf-8"))
    names: set[str] = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            names.update(alias.name for alias in node.names)
        elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            names.add(node.module)
    return names


def _modules(package: str) -> list[Path]:
    return sorted((ROOT / package.replace(".", "/")).rglob("*.py"))


def test_core_imports_nothing_of_mapserver() -> None:
    offenders = [
        (str(p.relative_to(ROOT)), name)
        for p in _modules("core")
        for name in _imports(p)
        if name == "mapserver" or name.startswith("mapserver.")
    ]
    assert offenders == []


def test_ingest_store_merge_never_import_faces() -> None:
    forbidden = ("mapserver.api", "mapserver.cli", "mapserver.pipeline")
    offenders = [
        (str(p.relative_to(ROOT)), name)
        for pkg in ("mapserver.ingest", "mapserver.store", "mapserver.merge")
        for p in _modules(pkg)
        for name in _imports(p)
        if name.startswith(forbidden)
    ]
    assert offenders == []


def test_only_faces_import_faces() -> None:
    offenders = []
    for p in _modules("mapserver"):
        rel = p.relative_to(ROOT).as_posix()
        if rel.startswith(("mapserver/cli/", "mapserver/api/")):
            continue
        for name in _imports(p):
            if name.startswith(("mapserver.cli", "mapserver.api")):
                offenders.append((rel, name))
    assert offenders == []


def test_walker_sees_real_imports() -> None:
    """Guard against a walker that finds nothing: core/engine must import numpy."""
    assert any("numpy" in _imports(p) for p in _modules("core"))
