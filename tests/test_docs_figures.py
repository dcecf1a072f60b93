"""One figure, one value: a measured figure quoted in several places of the documentation says the
same thing everywhere (README.md, CONTRIBUTING.md, docs/*.md).

The registry below names the figures that are quoted more than once, each with the phrasings that
quote its *current* value (a regular expression whose group ``v`` is the value) and the command
that produces it. A historical value is written with its date or commit in another phrasing
("32-34 us at commit 89d872a") and is not matched. CONTRIBUTING.md ("Quoting measured figures")
explains the convention. Three checks:

* every registered figure has one value across all files (the check that found the issue-30
  contradictions: a ``push_imu`` cost of 141 us in one place and 32-34 us in another, an INRoL IMU
  noise scale of 19.2 in one bullet and 9.8 in the table below it);
* every phrasing still matches at least as often as registered, so a reworded quote cannot silently
  drop out of the check;
* every figure's command is listed in docs/reproducibility.md.

A planted contradiction is flagged (``test_detector_flags_a_planted_contradiction``), so the
first check can fail.
"""

from __future__ import annotations

import re
from dataclasses import dataclass
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]

#: number, optionally a range ``a–b`` (en dash or hyphen) or ``a ± b``
NUM = r"[0-9]+(?:\.[0-9]+)?(?:\s*(?:–|-|±)\s*[0-9]+(?:\.[0-9]+)?)?"


@dataclass(frozen=True)
class Figure:
    """A measured figure quoted in the documentation.

    Attributes
    ----------
    name : str
        Short identifier.
    patterns : tuple of (str, int)
        Regular expressions whose named group ``v`` captures the value, each with the number of
        matches it must have at least over all documentation files.
    command : str
        The command that produces the figure; docs/reproducibility.md must list it.
    """

    name: str
    patterns: tuple[tuple[str, int], ...]
    command: str


REGISTRY: tuple[Figure, ...] = (
    Figure(
        "push_imu CPU per call [us], 2-min simulated log, 200 Hz IMU",
        (
            (rf"`push_imu` call costs (?P<v>{NUM}) µs of CPU", 1),
            (rf"\*\*(?P<v>{NUM}) µs CPU per `push_imu` call\*\*", 1),
        ),
        "python benchmarks/bench_streaming.py",
    ),
    Figure(
        "push_range CPU per call [us], same run",
        ((rf"(?P<v>{NUM}) µs (?:CPU )?per `push_range`", 1),),
        "python benchmarks/bench_streaming.py",
    ),
    Figure(
        "INRoL IMU noise scale, batch calibrate defaults, full log",
        (
            (rf"INRoL (?P<v>{NUM}), ISAS-Walk {NUM}; simulated", 1),
            (r"\| IMU noise scale \(full log\) \| (?P<v>[^|]+?) \|", 1),
        ),
        "python benchmarks/check_calibrate_real.py DS --kind inrol",
    ),
    Figure(
        "ISAS-Walk IMU noise scale, batch calibrate defaults, full log",
        (
            (rf"INRoL {NUM}, ISAS-Walk (?P<v>{NUM}); simulated", 1),
            (r"\| IMU noise scale \(full log\)(?: \| [^|]+){3} \| (?P<v>[^|]+?) \|", 1),
        ),
        "python benchmarks/check_calibrate_real.py DS --kind isas",
    ),
    Figure(
        "INRoL ESKF ATE [m], examples/estimator_real.yaml, no alignment",
        (
            (r"INRoL env #1 [^|]*\| [^|]*\| ATE (?P<v>[0-9.]+) m", 1),
            (r"\| ATE batch \[m\] \(ESKF / multilateration\) \| [0-9.]+ \((?P<v>[0-9.]+) /", 2),
        ),
        "python benchmarks/real_data.py",
    ),
    Figure(
        "ISAS-Walk ESKF ATE [m], examples/estimator_isas.yaml, SE(3) alignment",
        (
            (r"ISAS-Walk1 [^|]*\| [^|]*\| ATE (?P<v>[0-9.]+) m", 1),
            (r"\| ATE batch \[m\] \(ESKF / multilateration\)(?: \| [^|]+){3} \| (?:\*\*)?[0-9.]+(?:\*\*)? \((?P<v>[0-9.]+) /", 2),
        ),
        "python benchmarks/real_data.py",
    ),
    Figure(
        "ISAS-Walk RPE over 1 m [m], with and without the SE(3) alignment",
        ((r"ISAS-Walk's RPE over 1 m is (?P<v>[0-9.]+ m with `--align se3` and [0-9.]+ m)", 1),),
        "python benchmarks/real_data.py",
    ),
    Figure(
        "ESKF sigma_scale (residuals' variance factor) on the shared real logs",
        ((rf"1\.0 on the simulated demo, (?P<v>{NUM}) on the real logs", 3),),
        "python benchmarks/acceptance_real.py",
    ),
    Figure(
        "clock false alarms out of 200 simulated null logs (coloured range noise)",
        (
            (rf"(?P<v>{NUM}) of 200 simulated null logs raises? a clock event", 2),
            (rf"\*\*(?P<v>{NUM}) of 200\*\* are\s+corrected", 1),
        ),
        "python benchmarks/check_clock_false_alarms.py --seeds 50",
    ),
    Figure(
        "fast test subset, wall time on the loaded 2-core machine [s]",
        ((r"fast subset[^.\n]{0,60}?(?P<v>[0-9]+) s wall", 2),),
        'pytest -n 2 -q -m "not slow"',
    ),
    Figure(
        "whole test suite, wall time on an idle 2-core machine [min]",
        ((r"whole suite[^.\n]{0,60}?(?P<v>[0-9.]+) min of wall on an idle", 2),),
        "pytest -n 2 -q",
    ),
)


def doc_texts(root: Path = ROOT) -> dict[str, str]:
    """{relative path: text} of every documentation file the check reads."""
    files = [root / "README.md", root / "CONTRIBUTING.md", *sorted((root / "docs").glob("*.md"))]
    return {str(p.relative_to(root)): p.read_text(encoding="utf-8") for p in files if p.exists()}


def _normalise(value: str) -> str:
    v = re.sub(r"\s+", " ", value.strip())
    v = re.sub(r"\s*(–|-)\s*(?=[0-9])", "–", v)  # 32-34, 32 – 34 -> 32–34
    return re.sub(r"\s*±\s*", " ± ", v)


def occurrences(texts: dict[str, str], figure: Figure) -> list[tuple[str, int, str, str]]:
    """Every quote of ``figure``: (file, line, pattern, normalised value)."""
    found = []
    for path, text in texts.items():
        for pattern, _ in figure.patterns:
            for m in re.finditer(pattern, text):
                line = text.count("\n", 0, m.start()) + 1
                found.append((path, line, pattern, _normalise(m.group("v"))))
    return found


def contradictions(texts: dict[str, str], registry=REGISTRY) -> dict[str, list[tuple[str, int, str]]]:
    """{figure name: [(file, line, value), ...]} for each figure quoted with more than one value."""
    out = {}
    for fig in registry:
        occ = occurrences(texts, fig)
        if len({v for *_, v in occ}) > 1:
            out[fig.name] = [(f, line, v) for f, line, _, v in occ]
    return out


def test_no_figure_quoted_with_two_values():
    bad = contradictions(doc_texts())
    assert not bad, "figures quoted with different values:\n" + "\n".join(
        f"  {name}: " + "; ".join(f"{f}:{line} -> {v}" for f, line, v in occ) for name, occ in bad.items()
    )


@pytest.mark.parametrize("figure", REGISTRY, ids=[f.name for f in REGISTRY])
def test_every_phrasing_still_matches(figure):
    texts = doc_texts()
    occ = occurrences(texts, figure)
    for pattern, at_least in figure.patterns:
        n = sum(1 for _, _, p, _ in occ if p == pattern)
        assert n >= at_least, (figure.name, pattern, n, at_least)


def test_every_figure_has_its_command_in_reproducibility():
    repro = (ROOT / "docs" / "reproducibility.md").read_text(encoding="utf-8")
    missing = [(f.name, f.command) for f in REGISTRY if f.command not in repro]
    assert not missing, missing


def test_detector_flags_a_planted_contradiction():
    fig = REGISTRY[0]
    same = {"a.md": "a `push_imu` call costs 38 µs of CPU", "b.md": "**38 µs CPU per `push_imu` call**"}
    assert contradictions(same, (fig,)) == {}
    planted = dict(same, **{"b.md": "x\n**32–34 µs CPU per `push_imu` call**"})
    bad = contradictions(planted, (fig,))
    assert bad == {fig.name: [("a.md", 1, "38"), ("b.md", 2, "32–34")]}
    # a dated historical value in another phrasing is not a quote of the current figure
    dated = dict(same, **{"c.md": "32-34 µs per call at commit 89d872a"})
    assert contradictions(dated, (fig,)) == {}
    # the value is normalised: "9.8±0.4" and "9.8 ± 0.4" are one value, "9.8 ± 0.5" is another
    scale = REGISTRY[2]
    ok = {"a.md": "INRoL 9.8±0.4, ISAS-Walk 2.9 ± 0.2; simulated", "b.md": "| IMU noise scale (full log) | 9.8 ± 0.4 |"}
    assert contradictions(ok, (scale,)) == {}
    ok["b.md"] = "| IMU noise scale (full log) | 9.8 ± 0.5 |"
    assert scale.name in contradictions(ok, (scale,))
