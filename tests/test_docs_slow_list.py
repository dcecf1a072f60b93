"""The list of slow tests in tests/conftest.py names tests that exist, so it cannot rot silently.

Each entry is a test module (``tests/test_x.py``) or a test in it (``tests/test_x.py::test_name``,
``tests/test_x.py::TestClass``, ``tests/test_x.py::TestClass::test_name``); a renamed or deleted test
would otherwise leave the slow subset growing into the fast one unnoticed. Checked statically (the
module's syntax tree), without importing the modules.
"""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

import conftest

ROOT = Path(__file__).resolve().parents[1]


def _defined(module: Path) -> dict[str, ast.AST]:
    """Top-level functions and classes of ``module`` by name."""
    tree = ast.parse(module.read_text(encoding="utf-8"))
    return {n.name: n for n in tree.body if isinstance(n, (ast.FunctionDef, ast.AsyncFunctionDef, ast.ClassDef))}


def test_slow_list_is_not_empty_and_has_no_duplicates():
    assert conftest.SLOW_TESTS
    assert len(set(conftest.SLOW_TESTS)) == len(conftest.SLOW_TESTS)


@pytest.mark.parametrize("entry", conftest.SLOW_TESTS)
def test_slow_entry_names_an_existing_test(entry):
    path, *names = entry.split("::")
    module = ROOT / path
    assert module.is_file() and module.name.startswith("test_"), f"{entry}: no test module {path}"
    scope = _defined(module)
    for name in names:
        assert name in scope, f"{entry}: {path} defines no {name!r}"
        node = scope[name]
        scope = _defined_in_class(node) if isinstance(node, ast.ClassDef) else {}


def _defined_in_class(cls: ast.ClassDef) -> dict[str, ast.AST]:
    return {n.name: n for n in cls.body if isinstance(n, (ast.FunctionDef, ast.AsyncFunctionDef, ast.ClassDef))}


def test_matching_rule():
    m = conftest.is_listed
    listed = ("tests/test_a.py", "tests/test_b.py::test_x")
    assert m("tests/test_a.py::test_anything[1]", listed)
    assert m("tests/test_b.py::test_x", listed)
    assert m("tests/test_b.py::test_x[param-2]", listed)
    assert not m("tests/test_b.py::test_x_other", listed)
    assert not m("tests/test_ab.py::test_x", listed)
    assert not m("tests/test_b.py::test_y", listed)
