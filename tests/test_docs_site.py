"""The README stays short and its commands stay the project's; the documentation site is whole.

Static checks, no MkDocs run (CI runs ``mkdocs build --strict``, which also checks links, anchors
and the API reference's docstrings):

* the README's two set-up commands are there verbatim, and ``.ci/run`` runs the test command
  exactly;
* the README is at most 250 lines and every relative link in it (and in the docs pages) names a file
  that exists;
* every page under docs/ is in the site's navigation (``mkdocs.yml``), and the API reference
  (docs/api.md) documents every public name of ``uwbimu``.
"""

from __future__ import annotations

import re
from pathlib import Path

import pytest
import yaml

import uwbimu

ROOT = Path(__file__).resolve().parents[1]
README = ROOT / "README.md"
DEMO_COMMAND = "pip install -e . && uwbimu demo"
TEST_COMMAND = 'pip install -e ".[dev]" && pytest -n 2 -q'
LINK = re.compile(r"\[[^\]]*\]\(([^)\s]+)\)")


def _code_lines(text: str) -> list[str]:
    """Lines inside fenced code blocks."""
    return [line.strip() for block in re.findall(r"```[a-z]*\n(.*?)```", text, re.S) for line in block.splitlines()]


def test_readme_keeps_the_two_set_up_commands():
    code = _code_lines(README.read_text(encoding="utf-8"))
    assert DEMO_COMMAND in code
    assert TEST_COMMAND in code


def test_ci_runs_the_readme_test_command_exactly():
    lines = [line.strip() for line in (ROOT / ".ci" / "run").read_text(encoding="utf-8").splitlines()]
    assert TEST_COMMAND in lines
    assert "mkdocs build --strict" in lines


def test_readme_is_short():
    n = len(README.read_text(encoding="utf-8").splitlines())
    assert n <= 250, f"README.md has {n} lines; move detail into docs/ (the site)"


def _relative_links(path: Path) -> list[tuple[int, str]]:
    text = path.read_text(encoding="utf-8")
    out = []
    for m in LINK.finditer(text):
        target = m.group(1)
        if re.match(r"[a-z]+:", target) or target.startswith("#"):
            continue  # URLs and in-page anchors (MkDocs checks the anchors)
        out.append((text.count("\n", 0, m.start()) + 1, target.split("#", 1)[0]))
    return out


@pytest.mark.parametrize(
    "page", [README, ROOT / "CONTRIBUTING.md", *sorted((ROOT / "docs").glob("*.md"))], ids=lambda p: p.name
)
def test_relative_links_resolve(page):
    broken = [(line, t) for line, t in _relative_links(page) if not (page.parent / t).exists()]
    assert not broken, f"{page.relative_to(ROOT)}: links to missing files (line, target): {broken}"


def _nav_pages(nav) -> list[str]:
    if isinstance(nav, str):
        return [nav]
    if isinstance(nav, list):
        return [p for item in nav for p in _nav_pages(item)]
    if isinstance(nav, dict):
        return [p for value in nav.values() for p in _nav_pages(value)]
    return []


def test_every_docs_page_is_in_the_navigation():
    config = yaml.safe_load((ROOT / "mkdocs.yml").read_text(encoding="utf-8").replace("!!python", "#"))
    nav = set(_nav_pages(config["nav"]))
    pages = {p.name for p in (ROOT / "docs").glob("*.md")}
    assert pages - nav == set(), f"pages missing from mkdocs.yml nav: {sorted(pages - nav)}"
    assert nav - pages == set(), f"nav entries without a page: {sorted(nav - pages)}"


def test_api_reference_documents_every_public_name():
    text = (ROOT / "docs" / "api.md").read_text(encoding="utf-8")
    documented = set(re.findall(r"^### `uwbimu\.(\w+)`", text, re.M))
    targets = set(re.findall(r"^::: ([\w.]+)", text, re.M))
    public = set(uwbimu.__all__) - {"__version__"}
    assert documented == public
    for name in public:
        module, attr = uwbimu._EXPORTS[name].split(":")
        assert f"{module}.{attr}" in targets, name
