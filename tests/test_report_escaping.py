"""The HTML report is rendered by jinja2 with autoescape (issue 15 item 7): input text cannot inject markup."""

from __future__ import annotations

import re

from pathlib import Path

import pandas as pd
import yaml

from uwbimu.eval.report import render_report

EVIL = '<script>alert("x")</script>'


def test_text_from_the_output_folder_is_escaped(tmp_path):
    out = tmp_path / "out"
    out.mkdir()
    (out / "calibration.yaml").write_text(yaml.safe_dump({
        "lever_arm": [0.1, 0.0, 0.0], "lever_arm_sd": [0.01, 0.01, 0.01], "time_offset": 0.0,
        "time_offset_sd": 0.001, "lever_arm_mode": EVIL, "warnings": [EVIL]}))
    pd.DataFrame({"t": [0.0, 0.1], "anchor": [EVIL, "A1"], "range": [1.0, 2.0], "predicted": [1.0, 2.0],
                  "innovation": [0.01, -0.01], "nis": [0.5, 0.4], "accepted": [True, True]}).to_csv(
        out / "residuals.csv", index=False)
    html = render_report(out, title=EVIL)
    assert "<script>" not in html
    assert html.count("&lt;script&gt;") >= 4  # title (twice), mode, warning, anchor name
    assert re.search(r'<div class="warn" data-warning-kind="estimator_warning"[^>]*><code>estimator_warning</code> '
                     r'\(calibration.yaml\): &lt;script&gt;', html)


def test_templates_ship_with_the_package():
    import uwbimu.eval

    folder = Path(uwbimu.eval.__file__).parent / "templates"
    assert {p.name for p in folder.glob("*.j2")} == {"report.html.j2", "blocks.html.j2"}
    pyproject = (Path(__file__).resolve().parents[1] / "pyproject.toml").read_text()
    assert '"eval/templates/*.j2"' in pyproject and '"jinja2' in pyproject


def test_convergence_reads_the_columns_the_estimator_writes(tmp_path):
    """The report reads lx, ly, lz, td (+ sd_) from the states.csv of `uwbimu estimate`, no guessed names."""
    import uwbimu
    from uwbimu.eval.report import CAL_COLUMNS

    ds = uwbimu.simulate(uwbimu.builtin_scenario("calibration-flight").model_copy(update={"duration": 20.0}))
    res = uwbimu.run_eskf(ds, uwbimu.EskfOptions())
    uwbimu.write_estimate(res, ds, tmp_path / "est", plots=False)
    states = pd.read_csv(tmp_path / "est" / "states.csv", nrows=2)
    assert set(CAL_COLUMNS) | {f"sd_{c}" for c in CAL_COLUMNS} <= set(states.columns)
    html = render_report(tmp_path / "est")
    assert 'id="fig-convergence"' in html
