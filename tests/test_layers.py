"""The package graph is one-way: every import between the units of ``core`` and ``mapserver`` is in a table.

A *unit* is ``core`` (one unit: its inner structure is its own), the ``mapserver`` package itself (its
``__init__``: the version), each package or top-level module directly under ``mapserver``, and the modules of a
package that :data:`ALLOWED` names on their own (``mapserver.processing.run``, ``mapserver.atlas.undo``, …: the
modules of ``processing``, ``atlas``, ``formats`` and ``evaluation.rpe`` keep their own rows). :data:`ALLOWED`
names, for every unit, the units it may import; imports inside a unit are free. Relative imports are resolved
against the importing module's package, and ``from pkg import name`` counts as an import of ``pkg.name`` when
that is a module. Two more rules: :data:`PRIVATE` modules are imported only inside their own unit (the store's
models and bulk SQL), and the libraries of :data:`LIBRARY_OWNERS` only by the units named there (SQL only in
the store). docs/architecture.md ("Packages and import direction") draws the same table.
"""

from __future__ import annotations

import ast
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
TOPS = ("core", "mapserver")

# ------------------------------------------------------------------------------------------------- the table

BASE = frozenset({"core", "mapserver", "mapserver.errors", "mapserver.bounds"})
"""What every unit of mapserver may import: the engine, the package's version, the exception family, the bounds
of values from outside."""

SHARED = frozenset({"mapserver.names", "mapserver.pairs", "mapserver.formats", "mapserver.formats.csv",
                    "mapserver.formats.g2o", "mapserver.plotting", "mapserver.statuses"})  # fmt: skip
"""Leaf modules the domain packages may use: map names, KEY=VALUE pairs, file formats, figures, merge statuses."""

HELPERS = SHARED | {"mapserver.params", "mapserver.processing.reckoning", "mapserver.evaluation"}
"""Every leaf module: the shared ones, choosing parameters, dead reckoning, evaluation against ground truth."""

DOMAIN = frozenset({"mapserver.ingest", "mapserver.store", "mapserver.merge"})
"""Reading logs, keeping maps, merging engine states: they never import each other."""

ORCHESTRATION = frozenset({"mapserver.processing.run", "mapserver.processing.live", "mapserver.atlas",
                           "mapserver.atlas.undo", "mapserver.report", "mapserver.processing.pipeline",
                           "mapserver.atlas.manual_links"})  # fmt: skip
"""The modules that run the domain packages together (each row below says which ones it uses)."""

FACES = ("mapserver.api", "mapserver.cli")

ALLOWED: dict[str, frozenset[str]] = {
    # the engine: pure computation
    "core": frozenset(),
    # leaves
    "mapserver": frozenset(),
    "mapserver.errors": frozenset(),
    "mapserver.bounds": frozenset(),
    "mapserver.processing": BASE,
    "mapserver.names": BASE,
    "mapserver.pairs": BASE,
    "mapserver.statuses": BASE,
    "mapserver.formats": BASE,
    "mapserver.formats.csv": BASE | {"mapserver.formats"},
    "mapserver.formats.g2o": BASE | {"mapserver.formats"},
    "mapserver.params": BASE | {"mapserver.pairs"},
    "mapserver.processing.reckoning": BASE,
    "mapserver.evaluation.rpe": BASE,
    "mapserver.plotting": BASE,
    "mapserver.evaluation": BASE | {"mapserver.formats", "mapserver.evaluation.rpe", "mapserver.plotting"},
    # domain packages
    "mapserver.ingest": BASE | SHARED,
    "mapserver.store": BASE | SHARED,
    "mapserver.merge": BASE | SHARED,
    # orchestration
    "mapserver.processing.run": BASE | HELPERS | {"mapserver.ingest"},
    "mapserver.atlas": BASE | HELPERS | {"mapserver.store", "mapserver.merge"},
    "mapserver.atlas.undo": BASE | HELPERS | {"mapserver.store", "mapserver.merge", "mapserver.atlas"},
    "mapserver.atlas.manual_links": BASE | HELPERS | {"mapserver.store", "mapserver.merge", "mapserver.atlas"},
    "mapserver.processing.live": BASE | HELPERS | {"mapserver.merge", "mapserver.atlas"},
    "mapserver.report": BASE | HELPERS | {"mapserver.ingest", "mapserver.store"},
    "mapserver.processing.pipeline": BASE | HELPERS | DOMAIN | {"mapserver.processing.run", "mapserver.processing.live",
                                                                "mapserver.atlas"},
    # faces
    "mapserver.api": BASE | HELPERS | DOMAIN | ORCHESTRATION,
    "mapserver.cli": BASE | HELPERS | DOMAIN | ORCHESTRATION | {"mapserver.api"},
}

SIDEWAYS: frozenset[tuple[str, str]] = frozenset({
    *((a, b) for a in DOMAIN for b in DOMAIN if a != b),
    ("mapserver.processing.run", "mapserver.store"),  # a log through the engine alone
    ("mapserver.processing.run", "mapserver.merge"),
    ("mapserver.processing.live", "mapserver.store"),  # the running session's store view goes through atlas
    ("mapserver.atlas", "mapserver.atlas.undo"),  # undo is built on atlas
    ("mapserver.atlas", "mapserver.processing.live"),
    ("mapserver.report", "mapserver.merge"),
    ("mapserver.api", "mapserver.cli"),
    *((unit, face) for unit in set(ALLOWED) - set(FACES) for face in FACES),
    *((unit, "mapserver.processing.pipeline")
      for unit in set(ALLOWED) - {"mapserver.processing.pipeline", *FACES}),
})  # fmt: skip
"""Imports the table must never allow (checked against :data:`ALLOWED`)."""

PRIVATE: dict[str, str] = {
    "mapserver.store.models": "mapserver.store",
    "mapserver.store.bulk": "mapserver.store",
}
"""Modules imported only inside their unit: the store's schema and its bulk SQL."""

LIBRARY_OWNERS: dict[str, frozenset[str]] = {
    "sqlalchemy": frozenset({"mapserver.store"}),
    "alembic": frozenset({"mapserver.store"}),
    "rosbags": frozenset({"mapserver.ingest"}),
    **{web: frozenset({"mapserver.api"}) for web in ("fastapi", "starlette", "uvicorn", "celery", "prometheus_client")},
    "matplotlib": frozenset({"mapserver.plotting"}),
}
"""Third-party libraries only these units import (``migrations/``, outside the walk, uses sqlalchemy too)."""

FORBIDDEN: dict[str, str] = {
    "matplotlib.pyplot": "pyplot keeps global state: draw on a figure of mapserver.plotting",
}
"""Modules no unit imports, and why."""

# ---------------------------------------------------------------------------------------------- the picture

GROUPS: tuple[tuple[str, frozenset[str]], ...] = (
    ("orchestration", ORCHESTRATION),
    ("domain", DOMAIN),
    ("leaves", HELPERS),
    ("shared", SHARED),
)
"""Names the picture gives to these sets of units (a row that allows all of one shows its name)."""

PICTURE_BEGIN = "<!-- tests/test_layers.py: picture begin -->"
PICTURE_END = "<!-- tests/test_layers.py: picture end -->"
ARCHITECTURE = ROOT / "docs" / "architecture.md"


def short(unit: str) -> str:
    """Return a unit's name in the picture: ``core``, ``mapserver``, else the part after ``mapserver.``."""
    return unit if unit in ("core", "mapserver") else unit.removeprefix("mapserver.")


def layer_of(unit: str, memo: dict[str, int] | None = None) -> int:
    """Return a unit's layer: 0 for a unit that imports no other, else one above the highest unit it may import."""
    memo = {} if memo is None else memo
    if unit not in memo:
        memo[unit] = 1 + max((layer_of(u, memo) for u in ALLOWED[unit]), default=-1)
    return memo[unit]


def _row(unit: str) -> str:
    """Return what a unit may import in the picture's words: the units, then the groups it has whole."""
    rest = set(ALLOWED[unit])
    if rest >= BASE and unit not in BASE:
        rest -= BASE
    names: list[str] = []
    for name, members in GROUPS:
        if members <= rest:
            rest -= members
            names.append(name)
    order = sorted(rest, key=lambda u: (-layer_of(u), short(u)))
    empty = "nothing of mapserver" if unit in BASE else "the base only"
    return " · ".join([*(short(u) for u in order), *names]) or empty


def picture() -> str:
    """Return the text picture of :data:`ALLOWED`: one row per unit, highest layer first (docs/architecture.md)."""
    width = max(len(short(u)) for u in ALLOWED)
    lines = [f"layer  {'unit'.ljust(width)}     may import (besides the base, which every unit outside it may import)"]
    for unit in sorted(ALLOWED, key=lambda u: (-layer_of(u), short(u))):
        lines.append(f"{layer_of(unit):>5}  {short(unit).ljust(width)} ──► {_row(unit)}")
    lines.append("")
    for name, members in (("base", BASE), *GROUPS):
        lines.append(f"{name}: {' · '.join(short(u) for u in sorted(members, key=lambda u: (-layer_of(u), short(u))))}")
    return "\n".join(lines)

# ------------------------------------------------------------------------------------------------ the walker


@dataclass(frozen=True)
class Edge:
    """One import: the importing file, its line, the importing module and the module imported."""

    path: str
    line: int
    importer: str
    imported: str


def module_name(path: Path, root: Path) -> str:
    """Return the dotted module name of a file under ``root`` (a package's ``__init__`` is the package)."""
    parts = list(path.relative_to(root).with_suffix("").parts)
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def is_module(name: str, root: Path) -> bool:
    """Return whether ``name`` is a module or package of the tree under ``root``."""
    base = root.joinpath(*name.split("."))
    return base.with_suffix(".py").is_file() or (base / "__init__.py").is_file()


def _from_base(node: ast.ImportFrom, importer: str, is_package: bool) -> str:
    """Return the absolute module a ``from ... import`` names (relative levels resolved against the package)."""
    if node.level == 0:
        return node.module or ""
    package = importer.split(".") if is_package else importer.split(".")[:-1]
    up = node.level - 1
    if up > len(package) - 1:
        msg = f"relative import beyond the top package in {importer}"
        raise ValueError(msg)
    base = package[: len(package) - up]
    return ".".join([*base, *([node.module] if node.module else [])])


def imports_of(path: Path, root: Path) -> Iterator[Edge]:
    """Yield every module a file imports (nested imports included), resolved to absolute dotted names, once a line."""
    importer = module_name(path, root)
    is_package = path.name == "__init__.py"
    rel = path.relative_to(root).as_posix()
    found: dict[tuple[int, str], None] = {}
    for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
        if isinstance(node, ast.Import):
            found.update({(node.lineno, alias.name): None for alias in node.names})
        elif isinstance(node, ast.ImportFrom):
            base = _from_base(node, importer, is_package)
            subs = (f"{base}.{alias.name}" for alias in node.names if alias.name != "*")
            found.update({(node.lineno, sub if is_module(sub, root) else base): None for sub in subs} or
                         {(node.lineno, base): None})  # fmt: skip
    for line, imported in sorted(found):
        yield Edge(rel, line, importer, imported)


def unit_of(module: str) -> str | None:
    """Return the unit of a module of core or mapserver (None for any other module): a module of a package that has
    a row of its own in :data:`ALLOWED` is its own unit, any other module belongs to its top package."""
    parts = module.split(".")
    if parts[0] == "core":
        return "core"
    if parts[0] == "mapserver":
        own = ".".join(parts[:3])
        return own if own in ALLOWED else ".".join(parts[:2])
    return None


def check(edge: Edge) -> str | None:
    """Return why an import breaks a rule (None when it is allowed)."""
    unit, target = unit_of(edge.importer), unit_of(edge.imported)
    where = f"{edge.path}:{edge.line}: {edge.importer} imports {edge.imported}"
    if unit is None:
        return None
    if target is None:
        for module, why in FORBIDDEN.items():
            if edge.imported == module or edge.imported.startswith(module + "."):
                return f"{where}: {why}"
        owners = LIBRARY_OWNERS.get(edge.imported.split(".")[0])
        if owners is not None and unit not in owners:
            return f"{where}: only {', '.join(sorted(owners))} may import {edge.imported.split('.')[0]}"
        return None
    if target != unit and target not in ALLOWED.get(unit, frozenset()):
        allowed = ", ".join(sorted(ALLOWED.get(unit, frozenset()))) or "nothing"
        return f"{where}: {unit} may not import {target} (it may import {allowed})"
    for private, owner in PRIVATE.items():
        if (edge.imported == private or edge.imported.startswith(private + ".")) and unit != owner:
            return f"{where}: {private} is private to {owner}"
    return None


def files(root: Path) -> list[Path]:
    """Return every Python file of core and mapserver under ``root``."""
    return sorted(p for top in TOPS for p in (root / top).rglob("*.py"))


def violations(root: Path) -> list[str]:
    """Return every broken rule in the tree under ``root``, one line each."""
    return [msg for p in files(root) for e in imports_of(p, root) if (msg := check(e)) is not None]


# ----------------------------------------------------------------------------------------------- the checks


def test_imports_follow_the_table() -> None:
    found = violations(ROOT)
    assert found == [], "imports that break the layering:\n" + "\n".join(found)


def test_the_table_names_every_unit() -> None:
    units = {unit_of(module_name(p, ROOT)) for p in files(ROOT)}
    missing, stale = sorted(str(u) for u in units - set(ALLOWED)), sorted(set(ALLOWED) - units)
    assert units == set(ALLOWED), f"add to ALLOWED: {missing}; remove from it: {stale}"


def test_the_table_keeps_the_sideways_rules() -> None:
    broken = sorted((a, b) for a, b in SIDEWAYS if b in ALLOWED[a])
    assert broken == []
    assert ALLOWED["core"] == frozenset()


def test_the_architecture_page_draws_the_table() -> None:
    """docs/architecture.md holds :func:`picture` as it is (``python tests/test_layers.py --write`` draws it there)."""
    text = ARCHITECTURE.read_text(encoding="utf-8")
    drawn = text.split(PICTURE_BEGIN, 1)[-1].split(PICTURE_END, 1)[0].strip().removeprefix("```").removesuffix("```")
    assert PICTURE_BEGIN in text and drawn.strip("\n") == picture(), "run `python tests/test_layers.py --write`"


def test_the_architecture_page_lists_every_unit() -> None:
    """The page's first block names every unit's file or folder (``mapserver/store/``, ``mapserver/params.py``)."""
    listing = ARCHITECTURE.read_text(encoding="utf-8").split("```", 2)[1]
    paths = {line.split()[0] for line in listing.splitlines() if line.strip()}
    for unit in ALLOWED:
        folder = unit.replace(".", "/")
        names = {f"{folder}/__init__.py"} if unit == "mapserver" else {f"{folder}/", f"{folder}.py"}
        assert names & paths, f"docs/architecture.md does not list {unit}"


def test_the_picture_puts_every_import_below_its_importer() -> None:
    for unit, allowed in ALLOWED.items():
        assert all(layer_of(u) < layer_of(unit) for u in allowed), unit
    assert {layer_of(u) for u in BASE} == {0} and layer_of("mapserver.cli") == max(map(layer_of, ALLOWED))


def test_walker_sees_real_imports() -> None:
    """Guard against a walker that finds nothing: core must import numpy, the store sqlalchemy."""
    edges = [e for p in files(ROOT) for e in imports_of(p, ROOT)]
    assert any(e.importer.startswith("core") and e.imported == "numpy" for e in edges)
    assert any(e.importer.startswith("mapserver.store") and e.imported.startswith("sqlalchemy") for e in edges)
    # ``from mapserver import atlas`` is an import of the module mapserver.atlas
    assert any(e.importer == "mapserver.processing.live" and e.imported == "mapserver.atlas" for e in edges)


# ------------------------------------------------------------------------- the checks fail on a bad import


def _tree(root: Path, sources: dict[str, str]) -> Path:
    """Write a small tree of core and mapserver packages (every folder a package) with these files."""
    for rel, text in {"core/__init__.py": "", "mapserver/__init__.py": "", **sources}.items():
        (root / rel).parent.mkdir(parents=True, exist_ok=True)
        (root / rel).write_text(text, encoding="utf-8")
    for folder in [p for top in TOPS for p in (root / top).rglob("*") if p.is_dir()]:
        (folder / "__init__.py").touch()
    return root


@pytest.mark.parametrize(
    ("sources", "expected"),
    [
        ({"core/a.py": "import mapserver.errors\n"}, "core may not import mapserver.errors (it may import nothing)"),
        ({"mapserver/ingest/a.py": "from mapserver.store import maps\n", "mapserver/store/maps.py": ""},
         "mapserver.ingest.a imports mapserver.store.maps: mapserver.ingest may not import mapserver.store"),
        ({"mapserver/ingest/a.py": "from ..store.maps import x\n", "mapserver/store/maps.py": ""},
         "mapserver.ingest.a imports mapserver.store.maps: mapserver.ingest may not import mapserver.store"),
        ({"mapserver/merge/sub/a.py": "from ... import store\n", "mapserver/store/__init__.py": ""},
         "mapserver.merge.sub.a imports mapserver.store: mapserver.merge may not import mapserver.store"),
        ({"mapserver/api/a.py": "from mapserver.store.models import Job\n", "mapserver/store/models.py": ""},
         "mapserver.store.models is private to mapserver.store"),
        ({"mapserver/atlas/__init__.py": "def f():\n    from sqlalchemy import select\n"},
         "only mapserver.store may import sqlalchemy"),
        ({"mapserver/plotting.py": "def f():\n    import matplotlib.pyplot as plt\n"},
         "mapserver.plotting imports matplotlib.pyplot: pyplot keeps global state"),
        ({"mapserver/store/export.py": "def f():\n    from matplotlib.figure import Figure\n"},
         "only mapserver.plotting may import matplotlib"),
        ({"mapserver/report.py": "from mapserver.processing import pipeline\n",
          "mapserver/processing/__init__.py": "", "mapserver/processing/pipeline.py": ""},
         "mapserver.report imports mapserver.processing.pipeline: mapserver.report may not import "
         "mapserver.processing.pipeline"),
        ({"mapserver/processing/run.py": "from mapserver.store import maps\n", "mapserver/store/maps.py": ""},
         "mapserver.processing.run may not import mapserver.store"),
    ],
)
def test_a_forbidden_import_is_found(tmp_path: Path, sources: dict[str, str], expected: str) -> None:
    found = violations(_tree(tmp_path, sources))
    assert len(found) == 1 and expected in found[0], found


def test_allowed_and_relative_imports_pass(tmp_path: Path) -> None:
    root = _tree(tmp_path, {
        "mapserver/store/maps.py": "from . import models\nfrom .models import Map\nimport sqlalchemy\n",
        "mapserver/store/models.py": "from mapserver.errors import StoreError\n",
        "mapserver/errors.py": "",
        "mapserver/atlas/__init__.py": "from mapserver.store import maps\nfrom core import Params\n",
        "mapserver/api/routes/a.py": "from ..deps import x\nfrom mapserver import atlas\n",
        "mapserver/api/deps.py": "",
    })  # fmt: skip
    assert violations(root) == []
    edges = {e.imported for p in files(root) for e in imports_of(p, root)}
    assert {"mapserver.store.models", "mapserver.api.deps", "mapserver.atlas"} <= edges


def draw_on_the_page() -> None:
    """Write :func:`picture` between the markers of docs/architecture.md."""
    text = ARCHITECTURE.read_text(encoding="utf-8")
    head, rest = text.split(PICTURE_BEGIN, 1)
    tail = rest.split(PICTURE_END, 1)[1]
    ARCHITECTURE.write_text(f"{head}{PICTURE_BEGIN}\n```\n{picture()}\n```\n{PICTURE_END}{tail}", encoding="utf-8")


if __name__ == "__main__":
    import sys

    draw_on_the_page() if "--write" in sys.argv[1:] else print(picture())
