"""README and docs are self-contained: every relative link and quoted repository path exists,
nothing points outside the repository or names a work item; every page is on the documentation
site (make docs); licence and citation files match pyproject."""

from __future__ import annotations

import json
import re
import tomllib
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
DOCS = [ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md")), *sorted((ROOT / "docs" / "studies").glob("*.md"))]


@pytest.mark.parametrize("page", DOCS, ids=lambda p: str(p.relative_to(ROOT)))
def test_no_reference_outside_the_repository(page):
    text = page.read_text()
    assert "shared/spec" not in text and "/work/" not in text
    for target in re.findall(r"\]\(([^)#]+)(?:#[^)]*)?\)", text):
        if target.startswith(("http://", "https://")):
            continue
        resolved = (page.parent / target).resolve()
        assert resolved.is_relative_to(ROOT), f"{page.name}: link out of the repository {target}"
        assert resolved.exists(), f"{page.name}: broken link {target}"


@pytest.mark.parametrize("page", DOCS, ids=lambda p: str(p.relative_to(ROOT)))
def test_no_issue_numbers(page):
    assert not re.search(r"\bissues?[- ]?#?\d", page.read_text(), flags=re.I), page.name


def test_every_docs_page_is_on_the_site():
    index = (ROOT / "docs" / "index.md").read_text()
    listed = set()
    for block in re.findall(r"```\{toctree\}\n(.*?)```", index, flags=re.S):
        listed.update(line.strip() for line in block.splitlines() if line.strip() and not line.startswith(":"))
    pages = ({page.stem for page in (ROOT / "docs").glob("*.md")} - {"index"}) | {"studies/index"}
    assert listed == pages, f"not on the site: {sorted(pages - listed)}; listed but missing: {sorted(listed - pages)}"


def test_readme_is_a_front_page():
    """At most 100 lines, the two commands, every user page linked, and no measured test-suite
    line (a count of tests and minutes that goes stale with every commit)."""
    text = (ROOT / "README.md").read_text()
    assert len(text.splitlines()) <= 100
    assert "make test" in text and "make demo" in text and "make docs" in text
    assert not re.search(r"\d+ passed|runs \d+ tests", text)
    for page in sorted((ROOT / "docs").glob("*.md")):
        if page.stem not in ("index", "api"):
            assert f"(docs/{page.name}" in text, f"README does not link {page.name}"


def test_quoted_repository_paths_exist():
    """Every repository path the pages quote exists, but for what a build writes (docs/_build)."""
    text = "\n".join(page.read_text() for page in DOCS)
    quoted = set(re.findall(r"`((?:homogenization|warp_hcell|training|docs|benchmarks|studies|tests)/[\w./-]+)`", text))
    quoted = {path for path in quoted if not path.startswith("docs/_build/")}
    missing = sorted(path for path in quoted if not (ROOT / path.split(":")[0]).exists())
    assert quoted and not missing


def test_model_description_covers_the_physics():
    model = (ROOT / "docs" / "model.md").read_text()
    for heading in ("Geometry", "Contact law", "Equilibrium", "Love-Weber", "volume rule", "References"):
        assert heading.lower() in model.lower()
    numbered = [int(n) for n in re.findall(r"^## (\d+)\.", model, flags=re.M)]
    assert numbered == list(range(1, 15))  # "spec section N" in code and docs resolves here


def test_licence_and_citation_match_pyproject():
    project = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]
    assert project["license"] == "MIT" and (ROOT / "LICENSE").read_text().startswith("MIT License")
    citation = (ROOT / "CITATION.cff").read_text()
    assert f"version: {project['version']}\n" in citation and "license: MIT\n" in citation
    assert "cff-version: 1.2.0" in citation


def test_quoted_tests_exist():
    """Every test a page names (``tests/FILE.py::test_name``, as in the benchmarks page's "What CI
    checks") is defined in that file, so that a renamed test cannot leave a claim unchecked."""
    text = "\n".join(page.read_text() for page in DOCS)
    named = set(re.findall(r"`(tests/[\w./-]+\.py)::(test_\w+)`", text))
    missing = [f"{path}::{name}" for path, name in sorted(named)
               if not re.search(rf"^def {name}\(", (ROOT / path).read_text(), re.M)]
    assert named and not missing, missing


NUMBER = r"\d+(?:\.\d+)?(?:e[+-]?\d+)?"


def readme_results() -> list[tuple[str, str, str]]:
    """The rows (what, result, backed by) of the README's Results table."""
    section = (ROOT / "README.md").read_text().split("\n## Results\n", 1)[1].split("\n## ", 1)[0]
    rows = [[cell.strip() for cell in line.strip().strip("|").split(" | ")]
            for line in section.splitlines() if line.startswith("| ")]
    assert rows[0] == ["what", "result", "backed by"], rows[0]
    return [tuple(row) for row in rows[1:]]


def test_readme_results_are_backed():
    """Every README result row names what backs it: a test that make test runs (its existence is
    checked by test_quoted_tests_exist), a committed benchmark output whose text holds every figure
    of the row's result, or a committed certificate whose worst figure is the row's. Prints the
    list (pytest -s)."""
    rows = readme_results()
    assert len(rows) >= 5
    for what, result, backed in rows:
        tests = re.findall(r"`(tests/[\w./-]+\.py::test_\w+)`", backed)
        outputs = re.findall(r"`(benchmarks/results/[\w.-]+)`", backed)
        certificates = re.findall(r"`(homogenization/data/[\w.-]+\.json)`", backed)
        assert tests or outputs or certificates, f"README result row without a backing: {what}"
        for output in outputs:
            text = (ROOT / output).read_text()
            assert re.search(r"`benchmarks/\w+\.py[^`]*`", backed), f"{what}: no command regenerates {output}"
            missing = [n for n in re.findall(NUMBER, result) if n not in text]
            assert not missing, f"{what}: {missing} not in {output}"
        for path in certificates:
            worst = json.loads((ROOT / path).read_text())["certificate"]["worst"] * 100
            quoted = re.search(rf"worst ({NUMBER}) %", result)
            assert quoted, f"{what}: no worst figure quoted for {path}"
            decimals = len(quoted.group(1).partition(".")[2])
            assert f"{worst:.{decimals}f}" == quoted.group(1), (what, worst, quoted.group(1))
        print(f"{what}\n    {result}\n    backed by: {', '.join(tests + outputs + certificates)}")


PAGE_WORDS = 3000
"""Most words of one reference or how-to page (``docs/*.md``); measurement campaigns go to docs/studies/."""
TOTAL_WORDS = 30000
"""Most words of all reference and how-to pages together."""


def test_reference_pages_are_short():
    """Word counts (``wc -w``) of the pages outside docs/studies/, printed (pytest -s) and bounded."""
    counts = {page.name: len(page.read_text().split()) for page in sorted((ROOT / "docs").glob("*.md"))}
    for name, words in sorted(counts.items(), key=lambda item: -item[1]):
        print(f"{words:6d}  docs/{name}")
    print(f"{sum(counts.values()):6d}  total outside docs/studies/")
    assert {name: words for name, words in counts.items() if words > PAGE_WORDS} == {}
    assert sum(counts.values()) <= TOTAL_WORDS


DOCSTRING_WORDS = 150
"""Most words of a function's, class's or field's docstring: its contract (module overviews may say more)."""


def test_docstrings_state_contracts_in_at_most_150_words():
    import ast  # noqa: PLC0415

    long = []
    for package in ("warp_hcell", "training", "homogenization"):
        for path in sorted((ROOT / package).rglob("*.py")):
            tree = ast.parse(path.read_text())
            for node in ast.walk(tree):
                body = getattr(node, "body", None)
                if not isinstance(body, list):
                    continue
                for i, child in enumerate(body):
                    if not (isinstance(child, ast.Expr) and isinstance(child.value, ast.Constant)
                            and isinstance(child.value.value, str)):
                        continue
                    if isinstance(node, ast.Module) and i == 0:
                        continue  # the module overview
                    words = len(child.value.value.split())
                    if words > DOCSTRING_WORDS:
                        long.append(f"{path.relative_to(ROOT)}:{child.lineno} ({words} words)")
    assert not long, long
