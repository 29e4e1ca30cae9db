"""The README and the manual's pages other than comcact.md and comper.md (which have their own tests) stay a manual:

* README.md at most README_LINES lines; each page at most MAX_LINES, not counting tables the code generates;
* no dated headings in the component pages (dated measurements belong to docs/studies/);
* the studies moved out of these pages have their four parts (question, set-up naming the commit, result,
  verdict) and are in the studies index;
* every relative link of the README, these pages and their studies reaches a file that exists;
* sim.md's parameter table is the one the code generates.

``python test/unit/test_docs_pages.py --write`` pastes the code's current table into sim.md.
"""
from __future__ import annotations

import re
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
for _p in (ROOT / "src" / "comper_msgs", ROOT / "src" / "comper_sim", ROOT / "src" / "comper_agent"):
    if str(_p) not in sys.path:
        sys.path.insert(0, str(_p))

DOCS = ROOT / "docs"
README = ROOT / "README.md"
PAGES = [DOCS / f"{name}.md" for name in ("agent-core", "architecture", "recording", "setup", "sim", "results",
                                           "troubleshooting")]
COMPONENTS = [p for p in PAGES if p.stem not in ("results",)]
STUDY_PREFIXES = ("agent-core-", "architecture-", "recording-", "setup-", "sim-")
STUDIES = sorted(p for p in (DOCS / "studies").glob("*.md") if p.name.startswith(STUDY_PREFIXES))
INDEX = DOCS / "studies" / "README.md"
README_LINES = 150
MAX_LINES = 350
PARTS = ("## Question", "## Set-up", "## Result", "## Verdict")
_LINK = re.compile(r"!?\[[^\]]*\]\(([^)\s]+)\)")
_BLOCK = re.compile(r"(<!-- generated: (.+?) -->\n)(.*?)(<!-- end generated -->)", re.DOTALL)


def manual_lines(text: str) -> int:
    """Lines of a page, not counting the parameter tables the code generates (agent-core.md's '## Parameters'
    section, '<!-- generated -->' blocks)."""
    text = _BLOCK.sub("", text)
    if "\n## Parameters\n" in text:
        head, _, rest = text.partition("\n## Parameters\n")
        after = rest.find("\n## ")
        text = head + (rest[after:] if after >= 0 else "")
    return len(text.splitlines())


def generated_tables() -> dict[str, str]:
    """Marker text -> the table the code generates for it (without its heading and docstring lines)."""
    from comper_agent.core.config import parameter_table_markdown
    from comper_sim.core.config import SimConfig

    def table(cls) -> str:
        lines = parameter_table_markdown(cls).splitlines()
        return "\n".join(lines[lines.index("| parameter | default | thesis | description | deviation |"):]) + "\n"
    return {"parameter_table_markdown(SimConfig)": table(SimConfig)}


def test_readme_is_a_front_page():
    n = len(README.read_text().splitlines())
    assert n <= README_LINES, f"README.md has {n} lines (at most {README_LINES}): move detail to docs/"


@pytest.mark.parametrize("page", PAGES, ids=lambda p: p.name)
def test_page_is_a_manual_not_a_notebook(page):
    text = page.read_text()
    n = manual_lines(text)
    assert n <= MAX_LINES, f"docs/{page.name} has {n} lines besides generated tables (at most {MAX_LINES})"
    if page in COMPONENTS:
        dated = [h for h in text.splitlines() if h.startswith("#") and re.search(r"\b20\d\d-\d\d-\d\d\b", h)]
        assert not dated, f"dated headings belong in docs/studies/: {dated}"


def test_manual_lines_skip_generated_tables():
    text = "# T\n\na\n## Parameters\n\n| x |\n| y |\n## Decisions\n\nb\n<!-- generated: g -->\n| z |\n<!-- end generated -->\n"
    assert manual_lines(text) == 7


@pytest.mark.parametrize("study", STUDIES, ids=lambda p: p.name)
def test_a_study_has_its_four_parts_and_the_commit_that_recorded_it(study):
    text = study.read_text()
    at = [text.find("\n" + part + "\n") for part in PARTS]
    assert all(i >= 0 for i in at) and at == sorted(at), f"{study.name}: needs {', '.join(PARTS)} in that order"
    assert re.search(r"`[0-9a-f]{7,40}`", text[at[1]:at[2]]), f"{study.name}: its set-up names no commit"
    assert f"]({study.name})" in INDEX.read_text(), f"{study.name} is not in docs/studies/README.md"


def test_the_studies_moved_out_of_these_pages_exist():
    assert {p.name.split("-")[0] for p in STUDIES} >= {"agent", "architecture", "recording", "sim"}


@pytest.mark.parametrize("doc", [README, *PAGES, *STUDIES], ids=lambda p: p.name)
def test_relative_links_resolve(doc):
    for target in _LINK.findall(doc.read_text()):
        if "://" in target or target.startswith(("#", "mailto:")):
            continue
        path = target.partition("#")[0]
        assert (doc.parent / path).exists(), f"{doc.name} links {target}, which does not exist"


def test_sim_parameter_table_is_the_one_the_code_generates():
    blocks = {m.group(2): m.group(3) for m in _BLOCK.finditer((DOCS / "sim.md").read_text())}
    for marker, table in generated_tables().items():
        assert marker in blocks, f"docs/sim.md has no '<!-- generated: {marker} -->' block"
        assert blocks[marker] == table, f"docs/sim.md: {marker} is stale (python test/unit/test_docs_pages.py --write)"


def write() -> None:
    page = DOCS / "sim.md"
    tables = generated_tables()
    page.write_text(_BLOCK.sub(lambda m: m.group(1) + tables.get(m.group(2), m.group(3)) + m.group(4),
                               page.read_text()))


if __name__ == "__main__":
    if "--write" in sys.argv:
        write()
