"""Units in brackets survive ``--help`` on every verb (issue 30 item 4).

Typer renders help texts as rich markup, which read "[s]", "[m]" or "[deg/s]" as style tags and
dropped them ("Window length [s]" came out as "Window length").  This test walks every command
and sub-command of the app, collects every bracketed token of its own help texts (the command's
docstring, each visible parameter's help) and checks that the rendered ``--help`` shows each one
at least as often as the sources use it.
"""

from __future__ import annotations

import re
from collections import Counter

import pytest
import typer
from typer.testing import CliRunner

from uwbimu.cli.main import app

runner = CliRunner()
BRACKET = re.compile(r"\[[^\[\]]+\]")
BOX = re.compile("[\u2500-\u257f]")  # the panels' box-drawing characters


def _nodes():
    """``(path, click command)`` of the root, every group and every leaf command."""
    root = typer.main.get_command(app)

    def walk(cmd, path):
        yield path, cmd
        for name, sub in (getattr(cmd, "commands", None) or {}).items():
            yield from walk(sub, path + [name])

    return list(walk(root, []))


def _flat(text: str) -> str:
    return " ".join(BOX.sub(" ", text).split())


def _expected(cmd) -> Counter:
    """Bracketed tokens of the help texts that ``cmd --help`` shows (whitespace normalised)."""
    texts = [(cmd.help or "").partition("\f")[0]]
    texts += [p.help for p in cmd.params if getattr(p, "help", None) and not getattr(p, "hidden", False)]
    return Counter(tok for t in texts for tok in BRACKET.findall(_flat(t)))


NODES = _nodes()


def test_the_walk_covers_the_verbs_and_their_units():
    paths = {" ".join(p) for p, _ in NODES}
    assert {"", "check", "estimate", "calibrate", "observability", "observability log", "plan calibration",
            "import cf-usdlog"} <= paths
    units = sum((_expected(c) for _, c in NODES), Counter())
    # the help texts do use bracketed units: the test below has something to check
    assert units["[s]"] >= 3 and units["[m]"] >= 3, units


@pytest.mark.parametrize("path,cmd", NODES, ids=[" ".join(p) or "uwbimu" for p, _ in NODES])
def test_help_shows_every_bracketed_unit(path, cmd):
    expected = _expected(cmd)
    r = runner.invoke(app, [*path, "--help"], env={"COLUMNS": "120"})
    assert r.exit_code == 0, r.output
    shown = _flat(r.output)
    missing = {tok: n for tok, n in expected.items() if shown.count(tok) < n}
    assert not missing, f"uwbimu {' '.join(path)} --help lost {missing}"
