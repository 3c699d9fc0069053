"""The house rules the code itself can check: layers one way, docstrings as contracts.

Layers: ``meshes`` (with the error types) -> ``models`` -> ``solvers`` -> the ``wrinkles`` app;
``validation`` (measurements for tests, benchmarks and the paper) sits on top: it may read
what the app writes, the app never imports it. Every import counts, lazy ones too.
"""

from __future__ import annotations

import ast
import re
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
PACKAGES = ("meshes", "models", "solvers", "wrinkles", "validation")
ALLOWED: dict[str, set[str]] = {
    "meshes": {"meshes"},
    "models": {"meshes", "models"},
    "solvers": {"meshes", "models", "solvers"},
    "wrinkles": {"meshes", "models", "solvers", "wrinkles"},
    "validation": {"meshes", "models", "solvers", "wrinkles", "validation"},
}
MAX_DOCSTRING_LINES = 40
DATED = re.compile(r"\b20\d\d-\d\d-\d\d\b|\b[Ss]ession \d|\bround \d+ of\b")


def library_files() -> list[Path]:
    return sorted(p for pkg in PACKAGES for p in (REPO / pkg).rglob("*.py"))


def imported_packages(tree: ast.AST) -> set[str]:
    """Top-level names of every absolute import in the module (nested imports too)."""
    found = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            found.update(alias.name.split(".")[0] for alias in node.names)
        elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
            found.add(node.module.split(".")[0])
    return found


def test_the_walk_finds_every_package() -> None:
    files = library_files()
    assert {p.relative_to(REPO).parts[0] for p in files} == set(PACKAGES)
    assert len(files) > 60


@pytest.mark.parametrize("package", PACKAGES)
def test_imports_run_one_way(package: str) -> None:
    wrong = []
    for path in (REPO / package).rglob("*.py"):
        used = imported_packages(ast.parse(path.read_text())) & set(PACKAGES)
        wrong += [f"{path.relative_to(REPO)} imports {p}" for p in used - ALLOWED[package]]
    assert wrong == []


def test_the_layer_check_sees_a_lazy_upward_import() -> None:
    tree = ast.parse("def f():\n    from solvers.body import Body\n")
    assert imported_packages(tree) & set(PACKAGES) - ALLOWED["models"] == {"solvers"}


def docstrings(tree: ast.AST) -> list[tuple[str, str]]:
    nodes = [tree, *(n for n in ast.walk(tree) if isinstance(
        n, ast.FunctionDef | ast.AsyncFunctionDef | ast.ClassDef))]
    out = []
    for node in nodes:
        text = ast.get_docstring(node, clean=False)
        if text is not None:
            out.append((getattr(node, "name", "<module>"), text))
    return out


def test_no_docstring_is_longer_than_a_contract() -> None:
    long = []
    for path in library_files():
        for name, text in docstrings(ast.parse(path.read_text())):
            lines = text.count("\n") + 1
            if lines > MAX_DOCSTRING_LINES:
                long.append(f"{path.relative_to(REPO)}:{name} has {lines} lines")
    assert long == []


def test_library_code_carries_no_dates_or_development_history() -> None:
    hits = []
    for path in library_files():
        for k, line in enumerate(path.read_text().splitlines(), 1):
            if DATED.search(line):
                hits.append(f"{path.relative_to(REPO)}:{k}: {line.strip()}")
    assert hits == []


def test_the_date_pattern_matches_what_it_must() -> None:
    assert DATED.search("measured 2026-11-25 on a quiet machine")
    assert DATED.search("the sweeps of session 5")
    assert not DATED.search("Grinspun et al. 2003, Tamstorf & Grinspun 2013")
