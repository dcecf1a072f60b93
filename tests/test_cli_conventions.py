"""CLI conventions (issue 15 item 5): --version, no type labels on flags, -o/--out for output folders."""

from __future__ import annotations

import click
import pytest
import typer
from typer.testing import CliRunner

from uwbimu import __version__
from uwbimu.cli.main import app

runner = CliRunner()


def _commands():
    root = typer.main.get_command(app)

    def walk(cmd, path):
        if isinstance(cmd, click.Group):
            for name, sub in cmd.commands.items():
                yield from walk(sub, path + [name])
        else:
            yield path, cmd

    return list(walk(root, []))


def test_version():
    r = runner.invoke(app, ["--version"])
    assert r.exit_code == 0 and r.output.strip() == f"uwbimu {__version__}"


@pytest.mark.parametrize("path,cmd", _commands(), ids=lambda v: " ".join(v) if isinstance(v, list) else "")
def test_help_has_no_flag_type_labels(path, cmd):
    r = runner.invoke(app, [*path, "--help"], terminal_width=100)
    assert r.exit_code == 0, r.output
    assert "<bool>" not in r.output


@pytest.mark.parametrize("path,cmd", _commands(), ids=lambda v: " ".join(v) if isinstance(v, list) else "")
def test_out_option_has_short_form(path, cmd):
    for p in cmd.params:
        if isinstance(p, click.Option) and "--out" in p.opts:
            assert "-o" in p.opts, f"uwbimu {' '.join(path)}: --out without -o"
