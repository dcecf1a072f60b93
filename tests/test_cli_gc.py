"""The CLI's garbage-collector tuning (:mod:`uwbimu.cli.main`): a verb runs with a larger young-generation
threshold and the previous thresholds come back after it, also when it fails; at exit the objects are frozen
so Python's finalisation does not walk them again."""

from __future__ import annotations

import gc
import subprocess
import sys

import pytest

from uwbimu.cli import main as M
from uwbimu.errors import InputError


def test_verb_runs_with_fewer_collections_and_restores_thresholds():
    seen = []
    before = gc.get_threshold()
    ok = M.guarded(lambda: seen.append(gc.get_threshold()) or 0)
    assert ok() == 0
    assert seen[0][0] >= M.GC_YOUNG_THRESHOLD and seen[0][1:] == before[1:]
    assert gc.get_threshold() == before

    def fails():
        seen.append(gc.get_threshold())
        raise InputError("bad input")

    with pytest.raises(M.typer.Exit) as exc:
        M.guarded(fails)()
    assert exc.value.exit_code == InputError.exit_code
    assert seen[1][0] >= M.GC_YOUNG_THRESHOLD
    assert gc.get_threshold() == before


def test_objects_frozen_at_exit():
    # atexit runs its handlers last registered first: this one, registered before the CLI's, runs after it
    code = ("import atexit, gc\n"
            "atexit.register(lambda: print(gc.get_freeze_count() > 0))\n"
            "import uwbimu.cli.main\n")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "True"
