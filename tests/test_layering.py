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
    "errors": 0, "optional": 0, "typed": 0, "models": 0, "_worker_env": 0,
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


# --- no side effects in the library (issue 15 item 6) ------------------------------------------
#: (file, function) pairs that change the environment on purpose, and run in worker processes only
WORKER_ONLY = {("_worker_env.py", "<module>"), ("studies/executors.py", "_one_blas_thread")}


def _is_environ(node) -> bool:
    return isinstance(node, ast.Attribute) and node.attr == "environ" and \
        isinstance(node.value, ast.Name) and node.value.id == "os"


def _side_effects(tree: ast.AST):
    """(function, line, what) for matplotlib.use, logger levels, basicConfig, os.environ writes,
    putenv and module-level rich Consoles."""
    scopes = {}
    for fn in ast.walk(tree):
        if isinstance(fn, (ast.FunctionDef, ast.AsyncFunctionDef)):
            for n in ast.walk(fn):
                scopes.setdefault(id(n), fn.name)
    for node in ast.walk(tree):
        where = scopes.get(id(node), "<module>")
        if isinstance(node, ast.Call) and isinstance(node.func, ast.Attribute):
            f = node.func
            if f.attr == "use" and isinstance(f.value, ast.Name) and f.value.id == "matplotlib":
                yield where, node.lineno, "matplotlib.use"
            if f.attr in ("setLevel", "basicConfig", "disable"):
                yield where, node.lineno, f"logging {f.attr}"
            if f.attr in ("setdefault", "pop", "update", "clear", "popitem") and _is_environ(f.value):
                yield where, node.lineno, f"os.environ.{f.attr}"
            if f.attr in ("putenv", "unsetenv") and isinstance(f.value, ast.Name) and f.value.id == "os":
                yield where, node.lineno, f"os.{f.attr}"
        if isinstance(node, (ast.Assign, ast.AugAssign, ast.Delete)):
            targets = node.targets if isinstance(node, (ast.Assign, ast.Delete)) else [node.target]
            for t in targets:
                if isinstance(t, ast.Subscript) and _is_environ(t.value):
                    yield where, node.lineno, "os.environ[...] write"
        if isinstance(node, ast.Assign) and where == "<module>" and isinstance(node.value, ast.Call):
            fn = node.value.func
            if (isinstance(fn, ast.Name) and fn.id == "Console") or (isinstance(fn, ast.Attribute) and fn.attr == "Console"):
                yield where, node.lineno, "module-level Console"


def test_library_has_no_side_effects_outside_cli():
    bad = []
    for path in SRC.rglob("*.py"):
        rel = str(path.relative_to(SRC))
        if rel.startswith("cli/"):
            continue
        for where, line, what in _side_effects(ast.parse(path.read_text())):
            if (rel, where) not in WORKER_ONLY:
                bad.append(f"{rel}:{line} ({where}): {what}")
    assert not bad, "library side effects:\n" + "\n".join(bad)


def test_cli_has_no_module_level_console():
    bad = [f"{p.name}:{line}" for p in (SRC / "cli").glob("*.py")
           for where, line, what in _side_effects(ast.parse(p.read_text())) if what == "module-level Console"]
    assert not bad, bad


def test_the_side_effect_finder_finds_them():
    code = ("import os, logging, matplotlib\nfrom rich.console import Console\nc = Console()\n"
            "matplotlib.use('Agg')\ndef f():\n    os.environ['X'] = '1'\n    os.environ.setdefault('Y', '1')\n"
            "    logging.getLogger('uwbimu').setLevel(10)\n")
    found = {what for _, _, what in _side_effects(ast.parse(code))}
    assert found == {"module-level Console", "matplotlib.use", "os.environ[...] write", "os.environ.setdefault",
                     "logging setLevel"}
