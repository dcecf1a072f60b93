"""CLI conventions (issue 15 item 5): --version, no type labels on flags, -o/--out for output folders."""

from __future__ import annotations

import pytest
import typer
from typer.testing import CliRunner

from uwbimu import __version__
from uwbimu.cli.main import app

runner = CliRunner()


def _commands():
    root = typer.main.get_command(app)

    def walk(cmd, path):
        # typer >= 0.2x ships its own click (typer._click): test for a group by its sub-commands
        if getattr(cmd, "commands", None):
            for name, sub in cmd.commands.items():
                yield from walk(sub, path + [name])
        else:
            yield path, cmd

    return list(walk(root, []))


def test_version():
    r = runner.invoke(app, ["--version"])
    assert r.exit_code == 0 and r.output.strip() == f"uwbimu {__version__}"


def test_every_verb_is_walked():
    names = {" ".join(p) for p, _ in _commands()}
    assert {"simulate", "estimate", "report", "place", "plan calibration", "observability log", "montecarlo"} <= names


@pytest.mark.parametrize("path,cmd", _commands(), ids=lambda v: " ".join(v) if isinstance(v, list) else "")
def test_help_has_no_flag_type_labels(path, cmd):
    r = runner.invoke(app, [*path, "--help"], terminal_width=100)
    assert r.exit_code == 0, r.output
    assert "<bool>" not in r.output


@pytest.mark.parametrize("path,cmd", _commands(), ids=lambda v: " ".join(v) if isinstance(v, list) else "")
def test_out_option_has_short_form(path, cmd):
    for p in cmd.params:
        if "--out" in getattr(p, "opts", ()):
            assert "-o" in p.opts, f"uwbimu {' '.join(path)}: --out without -o"


def test_errors_go_to_stderr_as_one_line_plus_hint(tmp_path):
    """A refusal is one 'uwbimu: ...' line on stderr (and a hint line), nothing on stdout, and its exit code."""
    bad = tmp_path / "bad.yaml"
    bad.write_text("duration: 5\nuwb:\n  sigma: -1\n")
    r = runner.invoke(app, ["simulate", str(bad), "--out", str(tmp_path / "o")])
    assert r.exit_code == 2 and r.stdout == ""
    lines = r.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("uwbimu: invalid configuration: ")  # ConfigError, exit 2
    assert "bad.yaml" in lines[0] and "line 3, field 'uwb.sigma'" in lines[0]
    # an output refusal: exit 4 with a hint naming --force
    out = tmp_path / "out"
    out.mkdir()
    (out / "plan.json").write_text("mine")  # a file of the verb's name that uwbimu did not write
    r = runner.invoke(app, ["plan", "seed-ocp", "--out", str(out)])
    assert r.exit_code == 4 and r.stdout == ""
    lines = r.stderr.strip().splitlines()
    assert len(lines) == 2 and lines[0].startswith("uwbimu: output refused: ") and lines[1].startswith("hint: ")
    assert "--force" in lines[1]


@pytest.mark.parametrize("args", [
    ["montecarlo", "--out", "o"],  # neither CONFIG nor --example
    ["observability", "log", "d", "--out", "o", "--window", "-1"],
    ["place", "--out", "o"],
    ["simulate", "hover"],
])
def test_usage_errors_exit_2_on_stderr(tmp_path, monkeypatch, args):
    monkeypatch.chdir(tmp_path)
    r = runner.invoke(app, args)
    assert r.exit_code == 2, r.output
    assert r.stdout == "" and r.stderr.startswith("uwbimu: usage error: ")


def test_report_out_is_a_folder_and_html_a_file(tmp_path):
    """report: -o/--out names the output folder (report.html inside), --html FILE a file."""
    from test_report_html import make_output

    est = make_output(tmp_path / "est", with_extras=False)
    r = runner.invoke(app, ["report", str(est), "-o", str(tmp_path / "rep")])
    assert r.exit_code == 0, r.output
    assert (tmp_path / "rep" / "report.html").is_file() and not (est / "report.html").exists()
    r = runner.invoke(app, ["report", str(est), "--html", str(tmp_path / "x" / "mine.html")])
    assert r.exit_code == 0, r.output
    assert (tmp_path / "x" / "mine.html").read_text().startswith("<!DOCTYPE html>")
    r = runner.invoke(app, ["report", str(est), "-o", str(tmp_path / "a"), "--html", str(tmp_path / "b.html")])
    assert r.exit_code == 2 and "not both" in r.stderr


def test_force_has_one_help_text():
    from uwbimu.cli.conventions import FORCE_HELP

    texts = {}
    for path, cmd in _commands():
        for p in cmd.params:
            if "--force" in getattr(p, "opts", ()) and path != ["place"]:  # place's options are frozen this round
                texts[" ".join(path)] = p.help
    assert len(texts) >= 10 and set(texts.values()) == {FORCE_HELP}, texts


def _clipped_table_lines(text: str) -> list[str]:
    """Table lines cut at the console edge, or cells shortened with an ellipsis."""
    return [ln for ln in text.splitlines()
            if (ln[:1] in "┏┃┡│└" and ln[-1:] not in "┓┃┩│┘") or ("…" in ln and ln[:1] in "┃│")]


def test_tables_fit_80_columns(tmp_path):
    """COLUMNS=80: every table of these verbs fits (headers wrap; no number or column is cut)."""
    from pathlib import Path

    examples = Path(__file__).resolve().parents[1] / "examples"
    ds, est = tmp_path / "ds", tmp_path / "est"
    runs = [
        ["simulate", "calibration-flight", "-o", str(ds)],
        ["check", str(ds)],  # the Streams table
        ["estimate", str(ds), "-o", str(est)],
        ["evaluate", str(est), "-g", str(ds)],
        ["repeatability", str(ds), "-o", str(est), "-k", "2"],
        ["observability", "structural", str(examples / "observability" / "theorem2_generic.yaml")],
        ["observability", "log", str(ds), "-o", str(tmp_path / "obs"), "--window", "20"],
        ["plan", "seed-ocp", "-o", str(tmp_path / "seed")],  # its headers were cut ("1/det…")
        ["place", "--example", "room", "-o", str(tmp_path / "room"), "--no-plots"],  # out-of-hull column
    ]
    for args in runs:
        r = runner.invoke(app, args, env={"COLUMNS": "80"})
        assert r.exit_code == 0, (args, r.output)
        assert max(len(ln) for ln in r.stdout.splitlines()) <= 80, args
        assert not _clipped_table_lines(r.stdout), (args, _clipped_table_lines(r.stdout))


def test_evaluate_out_is_the_output_folder(tmp_path):
    ds, est = tmp_path / "ds", tmp_path / "est"
    sc = tmp_path / "s.yaml"
    sc.write_text("duration: 20\n")
    assert runner.invoke(app, ["simulate", str(sc), "-o", str(ds)]).exit_code == 0
    assert runner.invoke(app, ["estimate", str(ds), "-o", str(est), "--no-plots"]).exit_code == 0
    r = runner.invoke(app, ["evaluate", str(est), "-g", str(ds), "-o", str(tmp_path / "ev"), "--no-plots"])
    assert r.exit_code == 0, r.output
    assert (tmp_path / "ev" / "evaluation.json").is_file() and not (est / "evaluation.json").exists()


def test_import_takes_its_destination_as_dst_or_out(tmp_path):
    from pathlib import Path

    excerpt = Path(__file__).resolve().parent / "data" / "inrol_excerpt"
    if not excerpt.is_dir():
        pytest.skip("no INRoL excerpt in tests/data")
    r = runner.invoke(app, ["import", "inrol", str(excerpt), "-o", str(tmp_path / "a")])
    assert r.exit_code == 0, r.output
    assert (tmp_path / "a" / "imu.csv").is_file()
    r = runner.invoke(app, ["import", "inrol", str(excerpt), str(tmp_path / "b"), "-o", str(tmp_path / "c")])
    assert r.exit_code == 2 and "once" in r.stderr


@pytest.mark.parametrize("path,cmd", _commands(), ids=lambda v: " ".join(v) if isinstance(v, list) else "")
def test_help_is_in_sentence_case(path, cmd):
    for p in cmd.params:
        h = getattr(p, "help", None)
        assert not h or h[0].isupper(), f"uwbimu {' '.join(path)} {p.name}: {h!r}"
