#!/usr/bin/env python3
"""Regenerate the parameter and profile tables the docs embed from the code (one definition per parameter: the
``param()`` fields of the config classes).

A generated block in a docs page looks like::

    <!-- generated: parameter_table_markdown(ComcactNodeConfig) -->
    ...the table...
    <!-- end generated -->

The expression after ``generated:`` (up to a ``;`` or the comment's end) is evaluated with the table functions and
config classes below; the block's body is replaced with its result.

    python scripts/docs_tables.py           # rewrite every stale block in docs/ and README.md
    python scripts/docs_tables.py --check   # exit 1 and name the stale blocks (what the docs tests do)
"""
from __future__ import annotations

import argparse
import re
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
BLOCK = re.compile(r"(<!-- generated: (?P<expr>[^;>]+?)\s*(?:;[^>]*)?-->\n)(?P<body>.*?)(<!-- end generated -->)",
                   re.S)


def namespace() -> dict:
    from comper_agent.core import config as agent_config
    from comper_agent.nodes import node_config
    from comper_memory.core import config as memory_config
    from comper_memory import memory_node
    from comper_sim.core import config as sim_config
    ns = {}
    for mod in (agent_config, node_config, memory_config, memory_node, sim_config):
        ns.update({k: getattr(mod, k) for k in dir(mod) if not k.startswith("_")})
    return ns


def render(text: str, ns: dict) -> tuple[str, list[str]]:
    """The text with every generated block rewritten, and the expressions whose blocks changed."""
    stale = []

    def one(m: re.Match) -> str:
        body = eval(m.group("expr"), ns)           # noqa: S307 - expressions from our own docs
        if body != m.group("body"):
            stale.append(m.group("expr"))
        return m.group(1) + body + m.group(4)

    return BLOCK.sub(one, text), stale


def pages() -> list[Path]:
    return sorted((ROOT / "docs").rglob("*.md")) + [ROOT / "README.md"]


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--check", action="store_true", help="only report stale blocks (exit 1 if any)")
    args = ap.parse_args(argv)
    ns, bad = namespace(), []
    for page in pages():
        text = page.read_text()
        new, stale = render(text, ns)
        bad += [f"{page.relative_to(ROOT)}: {e}" for e in stale]
        if stale and not args.check:
            page.write_text(new)
    for b in bad:
        print(("stale: " if args.check else "rewrote: ") + b)
    return 1 if (bad and args.check) else 0


if __name__ == "__main__":
    sys.exit(main())
