"""docs/comper.md and the COMPER studies: the page's parameter table is the code's, every relative link resolves,
and the studies index lists every COMPER study."""
import re
import sys
from pathlib import Path

_ROOT = Path(__file__).resolve().parents[2]
for _p in (_ROOT / "src" / "comper_msgs", _ROOT / "src" / "comper_agent"):
    if str(_p) not in sys.path:
        sys.path.insert(0, str(_p))

DOCS = _ROOT / "docs"
STUDIES = sorted((DOCS / "studies").glob("comper-*.md"))
_LINK = re.compile(r"\]\(([^)\s#]+)(?:#[^)]*)?\)")


def test_page_lists_every_node_parameter_as_the_code_describes_it():
    from comper_agent.core.config import parameter_table_markdown
    from comper_agent.node_config import ComperNodeConfig
    assert parameter_table_markdown(ComperNodeConfig) in (DOCS / "comper.md").read_text(), \
        "docs/comper.md's parameter table is stale (paste parameter_table_markdown(ComperNodeConfig))"


def test_relative_links_of_the_page_and_its_studies_resolve():
    assert STUDIES, "no docs/studies/comper-*.md"
    missing = []
    for doc in [DOCS / "comper.md", *STUDIES]:
        for target in _LINK.findall(doc.read_text()):
            if "://" in target:
                continue
            if not (doc.parent / target).exists():
                missing.append(f"{doc.relative_to(_ROOT)} -> {target}")
    assert not missing, missing


def test_studies_index_lists_every_comper_study_in_its_section():
    text = (DOCS / "studies" / "README.md").read_text()
    section = text.split("## COMPER (Atari and vector tasks)", 1)[1].split("\n## ", 1)[0]
    listed = set(re.findall(r"\]\((comper-[^)]+\.md)\)", section))
    assert listed == {p.name for p in STUDIES}


def test_each_study_states_question_set_up_result_and_verdict_with_a_commit():
    for study in STUDIES:
        text = study.read_text()
        for part in ("**Question.**", "**Set-up.**", "## Result", "## Verdict"):
            assert part in text, f"{study.name} lacks {part}"
        setup = text.split("**Set-up.**", 1)[1].split("## Result", 1)[0]
        assert re.search(r"`[0-9a-f]{7}`", setup), f"{study.name}: no commit in its set-up"
