"""The size rules of issue #17 over every Python module under src/ (no exceptions list):

* no class has more than MAX_METHODS methods (every ``def`` in its body: properties, dunders and
  no-op hooks count too);
* a module over MAX_LINES lines says at its top why: a line of its docstring that starts with
  ``Size:`` (for example "Size: one node runs four variants ...; splitting them would repeat ...").

``python test/unit/test_structure.py`` prints the table (methods per class, lines per module) the
rules are checked on, largest first.
"""
from __future__ import annotations

import ast
import re
import sys
from pathlib import Path

import pytest

MAX_METHODS = 25
MAX_LINES = 400
SRC = Path(__file__).resolve().parents[2] / "src"
_SIZE_NOTE = re.compile(r"^Size: \S", re.MULTILINE)


def modules() -> list[Path]:
    """Every Python file of the packages' sources (setup.py files included)."""
    return sorted(p for p in SRC.rglob("*.py") if "__pycache__" not in p.parts)


def method_counts(path: Path) -> dict[str, int]:
    """'Class' (or 'Outer.Inner') -> the number of functions defined directly in its body."""
    out: dict[str, int] = {}

    def visit(node: ast.AST, prefix: str) -> None:
        for child in ast.iter_child_nodes(node):
            if isinstance(child, ast.ClassDef):
                name = prefix + child.name
                out[name] = sum(isinstance(x, (ast.FunctionDef, ast.AsyncFunctionDef)) for x in child.body)
                visit(child, name + ".")
            elif isinstance(child, (ast.FunctionDef, ast.AsyncFunctionDef)):
                visit(child, prefix + child.name + ".<locals>.")

    visit(ast.parse(path.read_text(encoding="utf-8"), str(path)), "")
    return out


def line_count(path: Path) -> int:
    return len(path.read_text(encoding="utf-8").splitlines())


def says_why_long(path: Path) -> bool:
    doc = ast.get_docstring(ast.parse(path.read_text(encoding="utf-8"))) or ""
    return bool(_SIZE_NOTE.search(doc))


def _rel(path: Path) -> str:
    return str(path.relative_to(SRC))


def test_the_rules_see_the_whole_source_tree():
    names = {_rel(p) for p in modules()}
    assert "comper_agent/comper_agent/nodes/harness.py" in names and "comper_memory/comper_memory/core/memory.py" in names
    assert len(names) > 50
    counts = method_counts(SRC / "comper_agent/comper_agent/nodes/harness.py")
    assert 10 < counts["LearnerHarness"] <= MAX_METHODS


def test_method_counting_counts_every_def_in_the_class_body(tmp_path):
    f = tmp_path / "m.py"
    f.write_text("class A:\n    x = 1\n    def a(self): pass\n    @property\n    def b(self): return 1\n"
                 "    async def c(self): pass\n    class B:\n        def d(self): pass\n"
                 "def f():\n    class C:\n        def e(self): pass\n")
    assert method_counts(f) == {"A": 3, "A.B": 1, "f.<locals>.C": 1}


def test_size_note_is_a_line_of_the_module_docstring(tmp_path):
    f = tmp_path / "m.py"
    f.write_text('"""Title.\n\nSize: two parts that belong together.\n"""\n')
    assert says_why_long(f)
    f.write_text('"""Title. Size: not at a line start."""\n# Size: a comment is not the docstring\n')
    assert not says_why_long(f)


@pytest.mark.parametrize("path", modules(), ids=_rel)
def test_no_class_has_more_than_25_methods(path):
    over = {name: n for name, n in method_counts(path).items() if n > MAX_METHODS}
    assert not over, (f"{_rel(path)}: {over} methods (at most {MAX_METHODS}): split the class by "
                      "responsibility (docs/architecture.md, 'Size rules')")


@pytest.mark.parametrize("path", modules(), ids=_rel)
def test_a_long_module_says_why_at_its_top(path):
    n = line_count(path)
    assert n <= MAX_LINES or says_why_long(path), (
        f"{_rel(path)}: {n} lines (> {MAX_LINES}) and no 'Size: ...' paragraph in its docstring saying why "
        "it is one module; split it or state the reason (docs/architecture.md, 'Size rules')")


def table() -> str:
    rows = []
    for p in modules():
        rows += [(n, f"class {name}", _rel(p)) for name, n in method_counts(p).items()]
    rows.sort(reverse=True)
    mods = sorted(((line_count(p), _rel(p), says_why_long(p)) for p in modules()), reverse=True)
    out = [f"methods per class (limit {MAX_METHODS}):"]
    out += [f"  {n:4d}  {what}  ({where})" for n, what, where in rows[:20]]
    out += [f"lines per module (limit {MAX_LINES} without a 'Size:' note):"]
    out += [f"  {n:4d}  {where}{'  (Size: note)' if why else ''}" for n, where, why in mods[:20]]
    return "\n".join(out)


if __name__ == "__main__":
    print(table())
    sys.exit(0)
