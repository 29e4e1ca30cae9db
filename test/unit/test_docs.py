"""The README and docs/ are the product's manual, and stay one:

* every table a page embeds between ``<!-- generated: EXPR -->`` and ``<!-- end generated -->`` is what the code
  generates now (``python scripts/docs_tables.py`` rewrites them; parameters are defined once, in the config
  classes);
* README.md at most README_LINES lines; each component page at most MAX_LINES, not counting generated tables, and
  no dated headings (dated measurements belong to docs/studies/);
* every study has its four parts (question, set-up naming the commit that recorded it, result, verdict) and a line
  in the studies index, and the index links no study that does not exist;
* every relative link of the README, the pages and the studies reaches a file that exists, and a link to a heading
  of a page reaches a heading that exists.
"""
from __future__ import annotations

import re
import sys
from pathlib import Path

import pytest

from scaffolding import load_script

ROOT = Path(__file__).resolve().parents[2]
DOCS = ROOT / "docs"
README = ROOT / "README.md"
STUDIES_DIR = DOCS / "studies"
INDEX = STUDIES_DIR / "README.md"
STUDIES = sorted(p for p in STUDIES_DIR.glob("*.md") if p != INDEX)
PAGES = sorted(DOCS.glob("*.md"))
#: pages that are not component pages: the specification and the results tables (long by nature)
NOT_COMPONENTS = {"method.md", "results.md"}
README_LINES = 150
MAX_LINES = 350
PARTS = ("## Question", "## Set-up", "## Result", "## Verdict")
_LINK = re.compile(r"!?\[[^\]]*\]\(([^)\s]+)\)")
_TABLES = load_script("docs_tables")


def manual_lines(text: str) -> int:
    """Lines of a page without the tables the code generates."""
    return len(_TABLES.BLOCK.sub("", text).splitlines())


def slug(heading: str) -> str:
    """GitHub's anchor of a markdown heading."""
    return re.sub(r"[^\w\- ]", "", heading.strip().lstrip("#").strip().lower()).replace(" ", "-")


#: page -> the generated tables it must hold (each node's and learner's parameters, each node's profiles)
REQUIRED_TABLES = {
    "agent-core.md": ["'\\n'.join(parameter_table_markdown(c) for c in ALL_CONFIGS)"],
    "comcact.md": ["parameter_table_markdown(ComcactNodeConfig)", 'profile_table_markdown(ComcactNodeConfig, "comcact")'],
    "comper.md": ["parameter_table_markdown(ComperNodeConfig)", 'profile_table_markdown(ComperNodeConfig, "comper")'],
    "sim.md": ["parameter_table_markdown(SimConfig)"],
}


@pytest.mark.parametrize("page", sorted(REQUIRED_TABLES))
def test_each_parameter_and_profile_table_has_its_page(page):
    found = {m.group("expr") for m in _TABLES.BLOCK.finditer((DOCS / page).read_text())}
    missing = set(REQUIRED_TABLES[page]) - found
    assert not missing, f"docs/{page} lacks the generated tables {missing}"


@pytest.mark.parametrize("page", [README, *PAGES], ids=lambda p: p.name)
def test_generated_tables_are_the_code_s(page):
    _, stale = _TABLES.render(page.read_text(), _TABLES.namespace())
    assert not stale, f"{page.name}: stale generated tables {stale} (python scripts/docs_tables.py)"


def test_readme_is_a_front_page():
    n = len(README.read_text().splitlines())
    assert n <= README_LINES, f"README.md has {n} lines (at most {README_LINES}): move detail to docs/"


@pytest.mark.parametrize("page", [p for p in PAGES if p.name not in NOT_COMPONENTS], ids=lambda p: p.name)
def test_a_component_page_is_a_manual_not_a_notebook(page):
    text = page.read_text()
    n = manual_lines(text)
    assert n <= MAX_LINES, f"docs/{page.name} has {n} lines besides generated tables (at most {MAX_LINES})"
    dated = [h for h in text.splitlines() if h.startswith("#") and re.search(r"\b20\d\d-\d\d-\d\d\b", h)]
    assert not dated, f"dated headings belong in docs/studies/: {dated}"


def test_manual_lines_skip_generated_tables():
    assert manual_lines("# T\n\na\n<!-- generated: g -->\n| z |\n| y |\n<!-- end generated -->\nb\n") == 5


@pytest.mark.parametrize("study", STUDIES, ids=lambda p: p.name)
def test_a_study_has_its_four_parts_the_commit_that_recorded_it_and_an_index_line(study):
    text = study.read_text()
    at = [text.find("\n" + part + "\n") for part in PARTS]
    assert all(i >= 0 for i in at) and at == sorted(at), f"{study.name}: needs {', '.join(PARTS)} in that order"
    assert re.search(r"`[0-9a-f]{7,40}`", text[at[1]:at[2]]), f"{study.name}: its set-up names no commit"
    assert f"]({study.name})" in INDEX.read_text(), f"{study.name} is not in docs/studies/README.md"


def test_the_index_links_only_studies_that_exist():
    for name in re.findall(r"\]\(([^)]+\.md)\)", INDEX.read_text()):
        assert (STUDIES_DIR / name).is_file(), f"the studies index links {name}, which does not exist"


@pytest.mark.parametrize("doc", [README, *PAGES, *STUDIES], ids=lambda p: p.name)
def test_relative_links_resolve(doc):
    for target in _LINK.findall(doc.read_text()):
        if "://" in target or target.startswith("mailto:"):
            continue
        path, _, anchor = target.partition("#")
        resolved = (doc.parent / path).resolve() if path else doc
        assert resolved.exists(), f"{doc.name} links {target}, which does not exist"
        if anchor and resolved.suffix == ".md":
            headings = {slug(h) for h in resolved.read_text().splitlines() if h.startswith("#")}
            assert anchor in headings, f"{doc.name} links {target}: {resolved.name} has no such heading"


if __name__ == "__main__":
    sys.exit(pytest.main([__file__, "-q"]))
