"""The package layout holds: no import cycles, and no module or function too long to read.

The layers themselves (which package may import which) are import-linter's contracts in
pyproject.toml, run by ``make test``; see docs/architecture.md.
"""

from __future__ import annotations

import ast
from pathlib import Path

import grimp
import pytest

PACKAGE = Path(__file__).resolve().parents[2] / "calstation"

MAX_MODULE_LINES = 800
"""A module longer than this holds more than one concept: split it."""

MAX_FUNCTION_LINES = 100
"""A function longer than this does more than one job: give its parts names. A function's own
lines are counted, not those of functions or classes defined inside it (a typer command group's
commands, a FastAPI app's route handlers), which are measured on their own."""

ALLOWED: dict[str, str] = {}
"""Modules (path below calstation/) or functions (``path::qualified.name``) allowed past the
limits, each with the reason."""


GENERATED = PACKAGE / "storage" / "db" / "migrations" / "versions"
"""Alembic's revision scripts: generated, then history that is never edited."""


def _modules() -> list[Path]:
    return sorted(p for p in PACKAGE.rglob("*.py")
                  if "__pycache__" not in p.parts and GENERATED not in p.parents)


def _own_lines(node: ast.AST) -> int:
    """Lines of ``node`` less those of the functions and classes defined inside it."""
    total: int = node.end_lineno - node.lineno + 1  # type: ignore[attr-defined]
    return total - sum(
        inner.end_lineno - inner.lineno + 1  # type: ignore[attr-defined, misc]
        for inner in _nested_defs(node)
    )


def _nested_defs(node: ast.AST) -> list[ast.AST]:
    """The functions and classes defined directly inside ``node`` (not inside those)."""
    out: list[ast.AST] = []
    for child in ast.iter_child_nodes(node):
        if isinstance(child, ast.FunctionDef | ast.AsyncFunctionDef | ast.ClassDef):
            out.append(child)
        else:
            out += _nested_defs(child)
    return out


def _functions(tree: ast.AST, prefix: str = "") -> list[tuple[str, ast.AST]]:
    out = []
    for node in ast.iter_child_nodes(tree):
        if isinstance(node, ast.FunctionDef | ast.AsyncFunctionDef | ast.ClassDef):
            name = f"{prefix}{node.name}"
            if not isinstance(node, ast.ClassDef):
                out.append((name, node))
            out += _functions(node, name + ".")
        else:
            out += _functions(node, prefix)
    return out


def test_no_module_is_too_long() -> None:
    long = {}
    for path in _modules():
        rel = path.relative_to(PACKAGE).as_posix()
        lines = path.read_text().count("\n")
        if lines > MAX_MODULE_LINES and rel not in ALLOWED:
            long[rel] = lines
    assert not long, f"modules over {MAX_MODULE_LINES} lines: {long}"


def test_no_function_is_too_long() -> None:
    long = {}
    for path in _modules():
        rel = path.relative_to(PACKAGE).as_posix()
        for name, node in _functions(ast.parse(path.read_text())):
            lines = _own_lines(node)
            if lines > MAX_FUNCTION_LINES and f"{rel}::{name}" not in ALLOWED:
                long[f"{rel}::{name}"] = lines
    assert not long, f"functions over {MAX_FUNCTION_LINES} lines: {long}"


def test_the_measure_counts_a_functions_own_lines() -> None:
    tree = ast.parse(
        "def outer():\n"
        "    a = 1\n"
        "    def inner():\n"
        "        b = 2\n"
        "        return b\n"
        "    return a\n"
    )
    (_, outer), (_, inner) = _functions(tree)
    assert _own_lines(outer) == 3 and _own_lines(inner) == 3


def test_every_allowed_entry_exists_and_is_still_long() -> None:
    for entry in ALLOWED:
        path, _, name = entry.partition("::")
        source = (PACKAGE / path).read_text()
        if not name:
            assert source.count("\n") > MAX_MODULE_LINES, f"{entry} is short now: drop it"
            continue
        found = dict(_functions(ast.parse(source)))
        assert name in found, f"{entry} no longer exists: drop it"
        assert _own_lines(found[name]) > MAX_FUNCTION_LINES, f"{entry} is short now: drop it"


def test_there_are_no_import_cycles() -> None:
    graph = grimp.build_graph("calstation")
    modules = sorted(graph.modules)
    for module in modules:
        for imported in graph.find_modules_directly_imported_by(module):
            if imported == module or not imported.startswith("calstation"):
                continue
            if graph.chain_exists(importer=imported, imported=module):
                chain = graph.find_shortest_chain(importer=imported, imported=module)
                pytest.fail(f"import cycle: {module} → {' → '.join(chain or [])}")


def _replaces(tree: ast.AST) -> list[int]:
    """Lines of ``tree`` that call ``os.replace`` (the rename that puts a file in place)."""
    return [node.lineno for node in ast.walk(tree)
            if isinstance(node, ast.Call) and isinstance(node.func, ast.Attribute)
            and node.func.attr == "replace" and isinstance(node.func.value, ast.Name)
            and node.func.value.id == "os"]


def test_outputs_are_put_in_place_by_the_one_atomic_writer() -> None:
    """Only calstation/atomic.py renames a written file over its target: every other output goes
    through it, so that each one is checked (no device, FIFO or folder replaced), flushed, and
    the previous file kept on failure."""
    plugins = PACKAGE.parent / "plugins"
    files = [*_modules(), *sorted(p for p in plugins.rglob("*.py") if "tests" not in p.parts)]
    found = [f"{p.relative_to(PACKAGE.parent)}:{line}" for p in files
             if p != PACKAGE / "atomic.py" for line in _replaces(ast.parse(p.read_text()))]
    assert found == []
    assert _replaces(ast.parse((PACKAGE / "atomic.py").read_text()))  # the measure sees it


TESTS = PACKAGE.parent / "tests"
"""The suite: one folder per layer, ``support/`` for what its modules share."""


def _imported(tree: ast.AST) -> list[tuple[int, str]]:
    """(line, module) of every import in ``tree``, at any depth; a relative import as ``.name``."""
    found: list[tuple[int, str]] = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            found += [(node.lineno, alias.name) for alias in node.names]
        elif isinstance(node, ast.ImportFrom):
            base = "." * node.level + (node.module or "")
            found.append((node.lineno, base))
            # ``from tests.support import station``: the modules named after ``import``
            found += [(node.lineno, f"{base}.{alias.name}") for alias in node.names
                      if node.module and node.module.split(".")[0] == "tests"]
    return found


def _shares_wrongly(module: str) -> bool:
    """Whether importing ``module`` reaches into the suite other than through ``tests.support``:
    a test module, a conftest, a layer's folder, a relative import, or a helper not in support."""
    parts = module.split(".")
    if module.startswith("."):
        return True
    if any(p.startswith("test_") or p == "conftest" for p in parts):
        return True
    if parts[0] == "tests":
        return parts[:2] != ["tests", "support"] and parts != ["tests"]
    return False


def test_no_test_module_imports_another() -> None:
    """Test modules share helpers only through ``tests/support/`` and fixtures only through
    conftest files: no test module, conftest or helper imports a test module (nor a conftest,
    nor another layer's folder), no module of ``tests/support/`` defines a fixture, and every
    test module is in a layer's folder."""
    files = sorted(p for p in TESTS.rglob("*.py") if "__pycache__" not in p.parts)
    wrong = [f"{p.relative_to(TESTS.parent)}:{line} imports {module}" for p in files
             for line, module in _imported(ast.parse(p.read_text())) if _shares_wrongly(module)]
    assert wrong == []
    fixtures = [f"{p.relative_to(TESTS.parent)}:{node.lineno}"
                for p in sorted((TESTS / "support").glob("*.py"))
                for node in ast.walk(ast.parse(p.read_text()))
                if isinstance(node, ast.Attribute) and node.attr == "fixture"]
    assert fixtures == []
    flat = sorted(p.name for p in TESTS.glob("test_*.py"))
    assert flat == [], "a test module goes in the folder of the layer it tests (tests/<layer>/)"
    # the measure sees a test module imported, flat or from its layer's folder
    assert _shares_wrongly("test_station") and _shares_wrongly("tests.station.test_station")
    assert not _shares_wrongly("tests.support.station")
