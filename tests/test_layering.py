"""Imports go down the architecture picture in CONTRIBUTING.md, never up.

Every ``import uwbimu.X`` / ``from uwbimu.X import`` in ``src/uwbimu`` (module level or
inside functions) is checked against the layer of the importing package.
"""

from __future__ import annotations

import ast
from pathlib import Path

SRC = Path(__file__).resolve().parents[1] / "src" / "uwbimu"

# lower number = lower layer; a package may import its own layer or lower ones
LAYER = {
    "errors": 0, "optional": 0, "models": 0,
    "io": 1,
    "sim": 2, "estimation": 2, "observability": 2, "metrics": 2,
    "calibration": 3, "design": 3, "eval": 3, "studies": 3,
    "cli": 4,
}


def _package(path: Path) -> str:
    rel = path.relative_to(SRC).parts
    return rel[0].removesuffix(".py") if rel else ""


def _imported(tree: ast.AST):
    for node in ast.walk(tree):
        if isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            yield node.module, node.lineno
        elif isinstance(node, ast.Import):
            for a in node.names:
                yield a.name, node.lineno


def test_imports_only_go_down():
    bad = []
    for path in SRC.rglob("*.py"):
        pkg = _package(path)
        if pkg not in LAYER:
            continue
        for mod, line in _imported(ast.parse(path.read_text())):
            parts = mod.split(".")
            if parts[0] != "uwbimu" or len(parts) < 2 or parts[1] not in LAYER:
                continue
            if LAYER[parts[1]] > LAYER[pkg]:
                bad.append(f"{path.relative_to(SRC)}:{line} imports {mod}")
    assert not bad, "upward imports:\n" + "\n".join(bad)


def test_every_package_has_a_layer():
    pkgs = {p.name for p in SRC.iterdir() if p.is_dir() and (p / "__init__.py").exists()}
    assert pkgs - {"data"} <= set(LAYER), pkgs - set(LAYER)
