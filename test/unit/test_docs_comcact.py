"""docs/comcact.md is the manual of comcact_node and docs/studies/comcact-*.md hold its dated studies:

* the page's parameter and profile tables are the ones the code generates (parameter_table_markdown,
  profile_table_markdown), pasted between the page's ``<!-- generated: ... -->`` markers;
* the page stays a manual: at most MAX_LINES lines and no dated headings (dates belong to the studies);
* every study is in the studies index, has its four parts (question, set-up, result, verdict), names the commit that
  recorded it, and every link of the page and of the studies into docs/results/, docs/studies/ or the page's own
  sections reaches a file (and heading) that exists.

``python test/unit/test_docs_comcact.py --write`` pastes the code's current tables into the page.
"""
from __future__ import annotations

import re
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
for _p in (ROOT / "src" / "comper_msgs", ROOT / "src" / "comper_agent"):
    if str(_p) not in sys.path:
        sys.path.insert(0, str(_p))

import pytest

DOCS = ROOT / "docs"
PAGE = DOCS / "comcact.md"
INDEX = DOCS / "studies" / "README.md"
STUDIES = sorted((DOCS / "studies").glob("comcact-*.md"))
MAX_LINES = 350
PARTS = ("## Question", "## Set-up", "## Result", "## Verdict")
_LINK = re.compile(r"!?\[[^\]]*\]\(([^)\s]+)\)")
_BLOCK = re.compile(r"(<!-- generated: (.+?) -->\n)(.*?)(<!-- end generated -->)", re.DOTALL)


def generated_tables() -> dict[str, str]:
    """Marker text -> the table the code generates for it."""
    from comper_agent.core.config import parameter_table_markdown, profile_table_markdown
    from comper_agent.node_config import ComcactNodeConfig
    return {"parameter_table_markdown(ComcactNodeConfig)": parameter_table_markdown(ComcactNodeConfig),
            'profile_table_markdown(ComcactNodeConfig, "comcact")':
                profile_table_markdown(ComcactNodeConfig, "comcact")}


def slug(heading: str) -> str:
    """GitHub's anchor of a markdown heading."""
    s = re.sub(r"[^\w\- ]", "", heading.strip().lstrip("#").strip().lower())
    return s.replace(" ", "-")


def test_page_tables_are_the_ones_the_code_generates():
    text = PAGE.read_text()
    blocks = {m.group(2): m.group(3) for m in _BLOCK.finditer(text)}
    for marker, table in generated_tables().items():
        assert marker in blocks, f"docs/comcact.md has no '<!-- generated: {marker} -->' block"
        assert blocks[marker] == table, \
            f"docs/comcact.md: {marker} is stale (python test/unit/test_docs_comcact.py --write)"


def test_page_is_a_manual_not_a_notebook():
    lines = PAGE.read_text().splitlines()
    assert len(lines) <= MAX_LINES, f"docs/comcact.md has {len(lines)} lines (at most {MAX_LINES}): move results to a study"
    dated = [h for h in lines if h.startswith("#") and re.search(r"\b20\d\d-\d\d-\d\d\b", h)]
    assert not dated, f"dated headings belong in docs/studies/: {dated}"


def test_studies_exist_and_every_one_is_indexed():
    index = INDEX.read_text()
    assert len(STUDIES) >= 16
    for f in STUDIES:
        assert f"]({f.name})" in index, f"{f.name} is not in docs/studies/README.md"
    for name in re.findall(r"\]\((comcact-[^)]+\.md)\)", index):
        assert (DOCS / "studies" / name).is_file(), f"the index links {name}, which does not exist"


@pytest.mark.parametrize("study", STUDIES, ids=lambda p: p.name)
def test_a_study_has_its_four_parts_and_the_commit_that_recorded_it(study):
    text = study.read_text()
    at = [text.find("\n" + part + "\n") for part in PARTS]
    assert all(i >= 0 for i in at) and at == sorted(at), f"{study.name}: needs {', '.join(PARTS)} in that order"
    setup = text[at[1]:at[2]]
    assert re.search(r"`[0-9a-f]{7,40}`", setup), f"{study.name}: its set-up names no commit"


@pytest.mark.parametrize("doc", [PAGE, *STUDIES], ids=lambda p: p.name)
def test_links_into_results_studies_and_the_page_resolve(doc):
    headings = {slug(h) for h in PAGE.read_text().splitlines() if h.startswith("#")}
    for target in _LINK.findall(doc.read_text()):
        if "://" in target or target.startswith("#"):
            continue
        path, _, anchor = target.partition("#")
        resolved = (doc.parent / path).resolve()
        if not (resolved.is_relative_to(DOCS / "results") or resolved.is_relative_to(DOCS / "studies")
                or resolved == PAGE):
            continue
        assert resolved.exists(), f"{doc.name} links {target}, which does not exist"
        if resolved == PAGE and anchor:
            assert anchor in headings, f"{doc.name} links {target}: comcact.md has no such heading"


def write() -> None:
    """Paste the code's current tables between the page's markers."""
    tables = generated_tables()
    text = PAGE.read_text()
    PAGE.write_text(_BLOCK.sub(lambda m: m.group(1) + tables.get(m.group(2), m.group(3)) + m.group(4), text))


if __name__ == "__main__":
    if sys.argv[1:] == ["--write"]:
        write()
    else:
        print(__doc__)
