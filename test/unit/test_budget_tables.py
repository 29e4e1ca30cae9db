"""The memory budget study (docs/studies/memory-budget.md): its table is what benchmarks/budget_bench.py computes
from the per-run records committed under docs/results/budget/, and a run's figures are read from its records as
the protocol says (last three evaluations, identities per 1,000 environment transitions)."""
import json
import sys
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from scaffolding import load_benchmark  # noqa: E402

BUDGET = load_benchmark("budget_bench")


def test_the_study_table_is_the_records():
    text, stale = BUDGET.study_blocks(BUDGET.STUDY.read_text())
    assert "<!-- budget table: mujoco -->" in text
    assert not stale, f"the {stale} table of memory-budget.md is stale: python benchmarks/budget_bench.py --report"


@pytest.mark.parametrize("domain", sorted(BUDGET.DOMAINS))
def test_every_record_is_a_finished_run_of_the_grid(domain):
    tasks, steps, budgets = BUDGET.DOMAINS[domain]
    for rec in BUDGET.load(domain):
        assert rec["task"] in tasks and rec["steps"] == steps
        assert (rec["memory"], rec["budget"]) == ("full", None) or \
            (rec["memory"] in BUDGET.MEMORIES and rec["budget"] in budgets)
        assert rec["evals"][-1][0] >= steps and rec["memory_records"]


def test_run_figures_and_export(tmp_path):
    """A run folder as comcact_node writes it: eval and memory records in metrics.jsonl."""
    run = tmp_path / "runs" / "compact-5000-Hopper-v4-s3"
    run.mkdir(parents=True)
    lines = []
    for step in range(0, 50_001, 5000):
        lines.append({"kind": "eval", "step": step, "mean_return": step / 100, "std_return": 1.0})
        lines.append({"kind": "memory", "step": step, "identities": step // 4, "transitions_stored": 9 * step,
                      "bytes_used": 1000 * step, "evictions": max(0, step // 4 - 5000), "tm_sets": 3})
    (run / "metrics.jsonl").write_text("".join(json.dumps(x) + "\n" for x in lines))
    unfinished = tmp_path / "runs" / "fifo-5000-Hopper-v4-s4"
    unfinished.mkdir()
    (unfinished / "metrics.jsonl").write_text(json.dumps(lines[0]) + "\n")
    assert BUDGET.export(tmp_path / "runs", "mujoco", out=tmp_path / "rec") == ["compact-5000-Hopper-v4-s3"]
    rec = BUDGET.load("mujoco", where=tmp_path / "rec")[0]
    assert (rec["task"], rec["memory"], rec["budget"], rec["seed"]) == ("Hopper-v4", "compact", 5000, 3)
    f = BUDGET.run_figures(rec)
    assert f["end"] == 500.0 and f["last3"] == pytest.approx(450.0)
    assert f["per_1000"] == 250.0 and f["evictions"] == 7500 and f["bytes"] == 50_000_000
    md = BUDGET.table_markdown([rec, {**rec, "seed": 4}])
    assert "| Hopper-v4 | compact | 5,000 | 3, 4 | 500.0 [500.0, 500.0] | 450.0 [450.0, 450.0] |" in md


def test_the_verdict_rules_of_the_protocol():
    """Within 5 %: the lower end of the interval of (compact - full) at least -5 % of full's mean; above FIFO: the
    interval of (compact - FIFO) above 0. Under two seeds in a group: no verdict."""
    def cells(full, compact, fifo):
        return {("full", None): {"last3": full}, ("compact", 500): {"last3": compact}, ("fifo", 500): {"last3": fifo}}
    v = BUDGET.verdicts(cells([100.0, 102.0], [99.0, 101.0], [10.0, 12.0]), 500)
    assert v == {"within_5pct": True, "above_fifo": True}
    v = BUDGET.verdicts(cells([100.0, 102.0], [50.0, 101.0], [60.0, 90.0]), 500)
    assert v == {"within_5pct": False, "above_fifo": False}
    assert BUDGET.verdicts(cells([100.0], [99.0, 101.0], [10.0]), 500) == {}
