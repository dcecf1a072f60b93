"""Imports go down the architecture picture in CONTRIBUTING.md, never up, and not sideways.

Every ``import uwbimu.X`` / ``from uwbimu.X import`` in ``src/uwbimu`` (module level or
inside functions) is checked against the layer of the importing package or top-level module.
"""

from __future__ import annotations

import ast
from pathlib import Path

SRC = Path(__file__).resolve().parents[1] / "src" / "uwbimu"

# lower number = lower layer; a package may import its own layer's modules or lower ones
LAYER = {
    # generic, no physics: errors, typed results, optional dependencies, the executor (process pool, Dask)
    "errors": 0, "optional": 0, "typed": 0, "formatting": 0, "parallel": 0, "_worker_env": 0,
    "models": 0,
    "io": 1,
    "sim": 2, "estimation": 2, "observability": 2, "metrics": 2,
    "calibration": 3, "design": 3,
    # the estimator registry with every estimator (estimation's filters and the batch calibrator)
    "estimators": 4,
    "eval": 5, "studies": 5,
    "cli": 6,
}

#: Imports between two different packages of one layer (sideways) that are allowed: (importer, imported).
#: Every other sideways import fails like an upward one (``studies`` <-> ``eval`` was one; issue 31 item 4).
SIDEWAYS_OK = {("estimation", "metrics")}


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


def _bad_imports(pkg: str, tree: ast.AST) -> list[tuple[int, str, str]]:
    """(line, module, "up" or "sideways") of every import of ``tree`` (in package ``pkg``) that breaks the table."""
    out = []
    for mod, line in _imported(tree):
        parts = mod.split(".")
        if parts[0] != "uwbimu" or len(parts) < 2:
            continue
        target = parts[1]
        if target not in LAYER:
            out.append((line, mod, "unlisted"))
        elif LAYER[target] > LAYER[pkg]:
            out.append((line, mod, "up"))
        elif LAYER[target] == LAYER[pkg] and target != pkg and LAYER[pkg] > 0 and (pkg, target) not in SIDEWAYS_OK:
            out.append((line, mod, "sideways"))
    return out


def test_imports_only_go_down():
    bad = []
    for path in SRC.rglob("*.py"):
        pkg = _package(path)
        if pkg not in LAYER:
            continue
        for line, mod, what in _bad_imports(pkg, ast.parse(path.read_text())):
            bad.append(f"{path.relative_to(SRC)}:{line} imports {mod} ({what})")
    assert not bad, "imports against the layer table:\n" + "\n".join(bad)


def test_the_checker_finds_upward_and_sideways_imports():
    code = ("from uwbimu.studies import run_study\nimport uwbimu.cli.main\nfrom uwbimu.estimation import run_eskf\n"
            "from uwbimu.estimators import get_estimator\nfrom uwbimu.design import placement\n")
    found = {(mod, what) for _, mod, what in _bad_imports("calibration", ast.parse(code))}
    assert found == {("uwbimu.studies", "up"), ("uwbimu.cli.main", "up"), ("uwbimu.estimators", "up"),
                     ("uwbimu.design", "sideways")}
    # the two arrows of issue 31 item 4, as they were
    assert _bad_imports("studies", ast.parse("from uwbimu.eval.estimators import get_estimator")) == \
        [(1, "uwbimu.eval.estimators", "sideways")]
    assert _bad_imports("design", ast.parse("from uwbimu.studies.executors import execute")) == \
        [(1, "uwbimu.studies.executors", "up")]
    assert _bad_imports("studies", ast.parse("from uwbimu.estimators import get_estimator")) == []
    assert _bad_imports("calibration", ast.parse("from uwbimu.parallel import execute")) == []


def test_every_top_level_module_has_a_layer():
    mods = {p.name.removesuffix(".py") for p in SRC.iterdir()
            if (p.is_dir() and (p / "__init__.py").exists()) or (p.suffix == ".py" and p.name != "__init__.py")}
    assert mods - {"data"} <= set(LAYER), mods - set(LAYER)


# --- no side effects in the library (issue 15 item 6) ------------------------------------------
#: (file, function) pairs that change the environment on purpose, and run in worker processes only
WORKER_ONLY = {("_worker_env.py", "<module>"), ("parallel.py", "_one_blas_thread")}


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
