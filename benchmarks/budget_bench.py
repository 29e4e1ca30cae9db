#!/usr/bin/env python3
"""Return against memory budget: the compact memory against FIFO and a uniform reservoir of the same size
(docs/studies/memory-budget.md has the protocol, fixed before the first run).

One learner per domain, held fixed, only the memory changes:

* ``full``: the recommended profile as it ships (the whole run fits: nothing is evicted, nothing compacts at
  its fixed delta);
* at each reduced budget B (identities): ``fifo-B`` (delta 0, removal fifo: a FIFO replay of B transitions),
  ``reservoir-B`` (delta 0, removal reservoir: a uniform sample of every transition) and ``compact-B``
  (key_normalisation running, delta_rule nn_quantile at delta_quantile 0.1, removal coverage).

    python benchmarks/budget_bench.py --domain mujoco                      # 70 runs, 2 at a time (~13 h)
    python benchmarks/budget_bench.py --domain atari                       # 12 runs (~11 h)
    python benchmarks/budget_bench.py --domain mujoco --seeds 1 --only-print   # the commands, nothing run
    python benchmarks/budget_bench.py --export benchmarks/results/learning/budget-mujoco/runs   # finished runs
    python benchmarks/budget_bench.py --report                             # table + plots from the records

Runs go through benchmarks/learning_bench.py (MuJoCo; resumable: started again with the same --tag it skips
finished runs and continues stopped ones). ``--export`` copies each finished run's evaluations and memory records
into one small json per run under docs/results/budget/<domain>/ (kept in git); ``--report`` builds the study's
table from those files (rewriting the block between the markers in docs/studies/memory-budget.md; the unit test
test_budget_tables.py checks it is current) and one plot per task, return against budget, one line per memory.
"""
from __future__ import annotations

import argparse
import json
import re
import subprocess
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
RECORDS = ROOT / "docs" / "results" / "budget"
STUDY = ROOT / "docs" / "studies" / "memory-budget.md"
sys.path.insert(0, str(ROOT / "benchmarks"))

#: (tasks, steps, budgets) per domain: budgets are ~1/4 and ~1/10 of the run's transitions (Atari: steps are frames,
#: 4 a transition, and ~1/4 only)
DOMAINS = {"mujoco": (["Hopper-v4", "HalfCheetah-v4"], 50_000, [12_500, 5_000]),
           "atari": (["ALE/Seaquest-v5"], 100_000, [6_250])}
SEEDS = {"mujoco": 5, "atari": 3}
MEMORIES = ("fifo", "reservoir", "compact")


def memory_params(memory: str, budget: int) -> list[tuple[str, str]]:
    """The memory parameters of one cell of the grid (the learner's are the profile's)."""
    cap = [("rtm_capacity", str(budget)), ("max_store_batch", str(min(budget, 1000)))]
    if memory in ("fifo", "reservoir"):
        return cap + [("removal", memory), ("delta", "0.0")]
    if memory == "compact":
        # delta stays the profile's: before the rule's first freeze (256 identities) keys are raw and nothing
        # compacts; after it the rule's scale puts delta at the quantile, whatever its value
        return cap + [("removal", "coverage"), ("key_normalisation", "running"), ("delta_rule", "nn_quantile"),
                      ("delta_quantile", "0.1")]
    raise ValueError(memory)


def variants(budgets: list[int], sep: str = "-") -> dict[str, list[tuple[str, str]]]:
    """{name: memory parameters}: full, then memory-budget for each budget (atari_bench's names take '_')."""
    out = {"full": []}
    for b in budgets:
        for m in MEMORIES:
            out[f"{m}{sep}{b}"] = memory_params(m, b)
    return out


def atari_bench_cmd(args) -> list[str]:
    """comper_node's default profile on ALE (atari_100k) through atari_bench: its figure is the mean of the last 10
    training episodes, as in docs/results.md."""
    tasks, frames, budgets = DOMAINS["atari"]
    vs = variants(budgets, "_")
    cmd = [sys.executable, str(ROOT / "benchmarks" / "atari_bench.py"),
           "--games", *[t.split("/")[1].split("-")[0] for t in tasks], "--seeds", *map(str, range(args.seeds)),
           "--frames", str(frames), "--parallel", str(args.parallel), "--variants", *vs,
           "--out", args.out or str(ROOT / "benchmarks" / "results" / "atari" / args.tag)]
    for name, ps in vs.items():
        cmd += ["--variant", f"{name}=comper:" + ",".join(f"{k}={v}" for k, v in ps)]
    return cmd + (["--report-only"] if args.report_only else [])


def learning_bench_cmd(args) -> list[str]:
    tasks, steps, budgets = DOMAINS[args.domain]
    vs = variants(budgets)
    cmd = [sys.executable, str(ROOT / "benchmarks" / "learning_bench.py"), "--tasks", *tasks,
           "--seeds", str(args.seeds), "--total-steps", str(steps), "--eval-every", "5000", "--eval-episodes", "10",
           "--report-steps", str(steps), "--final-evals", "3", "--parallel", str(args.parallel),
           "--tag", args.tag, "--baseline", "full", "--algorithms", *vs]
    if args.out:
        cmd += ["--out", args.out]
    for name, ps in vs.items():
        cmd += ["--variant", f"{name}=comcact:" + ",".join(f"{k}={v}" for k, v in ps)]
    return cmd + (["--report-only"] if args.report_only else [])


# ---------------------------------------------------------------------------------------------- per-run records
def parse_name(name: str) -> tuple[str, int | None]:
    """'compact-5000' or 'compact_5000' -> ('compact', 5000); 'full' -> ('full', None)."""
    mem, _, b = name.replace("_", "-").partition("-")
    return mem, (int(b) if b else None)


def export(runs_dir: Path, domain: str, out: Path = RECORDS) -> list[str]:
    """One json per finished run of ``runs_dir`` (learning_bench's runs/ folder) in out/<domain>/: task, memory,
    budget, seed, steps, evaluations [step, mean, std] and the memory records at each evaluation. A run counts as
    finished when it has evaluated at its last step; runs still going are left for a later export."""
    import learning_bench as lb
    from comper_agent.nodes.run_io import MetricsLog
    tasks, steps, _ = DOMAINS[domain]
    names = {t.replace("/", "_"): t for t in tasks}
    written = []
    (out / domain).mkdir(parents=True, exist_ok=True)
    for d in sorted(Path(runs_dir).iterdir()):
        m = re.fullmatch(r"(?P<name>\w+(?:-\d+)?)-(?P<task>.+)-s(?P<seed>\d+)", d.name)
        if not m or m["task"] not in names:
            continue
        evals = lb.resumed_evals(MetricsLog.read(d / "metrics.jsonl", "eval", missing_ok=True))
        if not evals or evals[-1]["step"] < steps:
            continue
        mem, budget = parse_name(m["name"])
        rec = {"task": names[m["task"]], "memory": mem, "budget": budget, "seed": int(m["seed"]), "steps": steps,
               "evals": [[e["step"], e["mean_return"], e["std_return"]] for e in evals],
               "memory_records": lb.memory_summary(d / "metrics.jsonl")}
        (out / domain / f"{d.name}.json").write_text(json.dumps(rec, indent=None) + "\n")
        written.append(d.name)
    return written


def load(domain: str, where: Path = RECORDS) -> list[dict]:
    return [json.loads(p.read_text()) for p in sorted((where / domain).glob("*.json"))]


# ---------------------------------------------------------------------------------------------- the table
def run_figures(rec: dict, every: int = 5000, k: int = 3) -> dict:
    """One run's figures: return at the end, mean of the last k evaluations, and at the end identities per 1,000
    environment transitions, bytes held and evictions (from its last memory record)."""
    import learning_bench as lb
    ev = [tuple(e) for e in rec["evals"]]
    last = rec["memory_records"][-1] if rec["memory_records"] else {}
    ids = last.get("identities", last.get("replay_size"))
    return {"end": lb.return_at(ev, rec["steps"], every), "last3": lb.final_mean(ev, every, rec["steps"], k),
            "per_1000": None if ids is None else 1000.0 * ids / last["step"],
            "bytes": last.get("bytes_used", last.get("replay_bytes")), "evictions": last.get("evictions", 0)}


def _cell(vals) -> str:
    import learning_bench as lb
    if not vals:
        return "-"
    lo, hi = lb.bootstrap_ci(vals)
    return f"{np.mean(vals):,.1f} [{lo:,.1f}, {hi:,.1f}]"


def _diff(vals, ref) -> tuple[str, dict | None]:
    import learning_bench as lb
    if len(vals) < 2 or len(ref) < 2:
        return "-", None
    d = lb.difference(vals, ref)
    return f"{d['diff']:+,.1f} [{d['ci95'][0]:+,.1f}, {d['ci95'][1]:+,.1f}]", d


def summary(records: list[dict]) -> dict:
    """{task: {(memory, budget): {"seeds": [...], "end": [...], "last3": [...], "per_1000": [...], ...}}}"""
    out: dict = {}
    for r in sorted(records, key=lambda r: (r["task"], r["memory"], r["budget"] or 0, r["seed"])):
        f = run_figures(r)
        cell = out.setdefault(r["task"], {}).setdefault((r["memory"], r["budget"]), {
            "seeds": [], "end": [], "last3": [], "per_1000": [], "bytes": [], "evictions": []})
        cell["seeds"].append(r["seed"])
        for k, v in f.items():
            if v is not None:
                cell[k].append(v)
    return out


def verdicts(cells: dict, budget: int) -> dict:
    """The protocol's verdicts at one budget, on the last-3 mean: compact within 5 % of full (the lower end of the
    difference's interval at least -5 % of full's mean), and above FIFO / reservoir (interval above 0)."""
    full = cells.get(("full", None), {}).get("last3", [])
    comp = cells.get(("compact", budget), {}).get("last3", [])
    out = {}
    if len(full) >= 2 and len(comp) >= 2:
        _, d = _diff(comp, full)
        out["within_5pct"] = d["ci95"][0] >= -0.05 * abs(float(np.mean(full)))
    for other in ("fifo", "reservoir"):
        o = cells.get((other, budget), {}).get("last3", [])
        if len(o) >= 2 and len(comp) >= 2:
            out[f"above_{other}"] = _diff(comp, o)[1]["ci95"][0] > 0
    return out


def table_markdown(records: list[dict]) -> str:
    """The study's table: per task and memory, seeds, return at the end and over the last three evaluations (mean
    [95% CI]), the difference of the last-3 mean to full and (compact rows) to FIFO and the reservoir of the same
    budget, identities per 1,000 environment transitions, MB held and evictions at the end (means over seeds)."""
    if not records:
        return "No run has finished yet.\n"
    rows = ["| task | memory | budget | seeds | return at end | last 3 evaluations | - full | compact - FIFO | "
            "compact - reservoir | identities / 1,000 | MB held | evictions |",
            "|---|---|---|---|---|---|---|---|---|---|---|---|"]
    order = {"full": 0, "fifo": 1, "reservoir": 2, "compact": 3}
    for task, cells in summary(records).items():
        full = cells.get(("full", None), {}).get("last3", [])
        for (mem, budget), c in sorted(cells.items(), key=lambda kv: (-(kv[0][1] or 10**9), order[kv[0][0]])):
            vs_full = _diff(c["last3"], full)[0] if mem != "full" else ""
            vs = ["", ""]
            if mem == "compact":
                vs = [_diff(c["last3"], cells.get((o, budget), {}).get("last3", []))[0] for o in ("fifo", "reservoir")]
            mean = (lambda xs, f: f(np.mean(xs)) if xs else "-")
            rows.append(f"| {task} | {mem} | {'whole run' if budget is None else f'{budget:,}'} | "
                        f"{', '.join(map(str, c['seeds']))} | {_cell(c['end'])} | {_cell(c['last3'])} | {vs_full} | "
                        f"{vs[0]} | {vs[1]} | {mean(c['per_1000'], lambda v: f'{v:,.0f}')} | "
                        f"{mean(c['bytes'], lambda v: f'{v / 1e6:,.1f}')} | "
                        f"{mean(c['evictions'], lambda v: f'{v:,.0f}')} |")
    rows.append("")
    word = {True: "yes", False: "no", None: "not yet (under 2 seeds in a group)"}
    for task, cells in summary(records).items():
        for budget in sorted({b for (m, b) in cells if m == "compact"}, reverse=True):
            v = verdicts(cells, budget)
            rows.append(f"- {task} at {budget:,}: compact within 5 % of full: {word[v.get('within_5pct')]}; above "
                        f"FIFO: {word[v.get('above_fifo')]}; above the reservoir: {word[v.get('above_reservoir')]}.")
    return "\n".join(rows) + "\n"


def plot(records: list[dict], out_dir: Path) -> list[Path]:
    """One figure per task: the last-3 mean (and its interval) against the budget as a fraction of the run, one
    line per memory; full sits at 1 on every line."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import learning_bench as lb
    paths = []
    for task, cells in summary(records).items():
        full = cells.get(("full", None), {}).get("last3", [])
        steps = next(r["steps"] for r in records if r["task"] == task)
        fig, ax = plt.subplots(figsize=(6, 4))
        for mem in ("fifo", "reservoir", "compact"):
            pts = sorted((b / steps, c["last3"]) for (m, b), c in cells.items() if m == mem and c["last3"])
            if full:
                pts.append((1.0, full))
            if not pts:
                continue
            xs = [p[0] for p in pts]
            ms = [float(np.mean(p[1])) for p in pts]
            ci = [lb.bootstrap_ci(p[1]) for p in pts]
            ax.errorbar(xs, ms, yerr=[[m - c[0] for m, c in zip(ms, ci)], [c[1] - m for m, c in zip(ms, ci)]],
                        marker="o", capsize=3, label=mem)
        ax.set_xscale("log")
        ticks = sorted({b / steps for (_, b) in cells if b} | {1.0})
        ax.set_xticks(ticks, [f"1/{round(1 / t)}" if t < 1 else "whole run" for t in ticks])
        ax.minorticks_off()
        ax.set_xlabel("budget (identities, as a share of the run's transitions)")
        ax.set_ylabel("return, mean of the last 3 evaluations")
        ax.set_title(f"{task}: return against memory budget (95% CI)")
        ax.legend()
        fig.tight_layout()
        path = out_dir / f"budget_{task.replace('/', '_')}.png"
        fig.savefig(path, dpi=100)
        plt.close(fig)
        paths.append(path)
    return paths


TABLE_BLOCK = re.compile(r"(<!-- budget table: (?P<domain>\w+) -->\n)(?P<body>.*?)(<!-- end budget table -->)", re.S)


def study_blocks(text: str) -> tuple[str, list[str]]:
    """The study page with every budget table block rewritten from the records, and the domains that changed."""
    stale = []

    def one(m):
        body = table_markdown(load(m["domain"]))
        if body != m["body"]:
            stale.append(m["domain"])
        return m.group(1) + body + m.group(4)

    return TABLE_BLOCK.sub(one, text), stale


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--domain", choices=sorted(DOMAINS), default="mujoco")
    ap.add_argument("--seeds", type=int, default=None, help="seeds 0..N-1 (protocol: 5 on MuJoCo, 3 on Atari)")
    ap.add_argument("--parallel", type=int, default=2)
    ap.add_argument("--tag", default=None, help="the sweep's folder name (default budget-<domain>)")
    ap.add_argument("--out", default="", help="learning_bench's --out (default: its own)")
    ap.add_argument("--report-only", action="store_true", help="learning_bench's tables from the runs so far")
    ap.add_argument("--only-print", action="store_true", help="print the command, run nothing")
    ap.add_argument("--export", type=Path, default=None, metavar="RUNS_DIR",
                    help="copy the finished runs of RUNS_DIR into docs/results/budget/<domain>/ and stop")
    ap.add_argument("--report", action="store_true",
                    help="the table and plots from docs/results/budget/<domain>/ (rewrites the study's block)")
    args = ap.parse_args(argv)
    args.seeds = args.seeds or SEEDS[args.domain]
    args.tag = args.tag or f"budget-{args.domain}"
    if args.export:
        done = export(args.export, args.domain)
        print(f"exported {len(done)} finished run(s) to {RECORDS / args.domain}", flush=True)
        return 0
    if args.report:
        print(table_markdown(load(args.domain)), flush=True)
        for p in plot(load(args.domain), RECORDS / args.domain):
            print(f"wrote {p.relative_to(ROOT)}", flush=True)
        text, stale = study_blocks(STUDY.read_text())
        if stale:
            STUDY.write_text(text)
            print(f"rewrote the {', '.join(stale)} table of {STUDY.relative_to(ROOT)}", flush=True)
        return 0
    cmd = learning_bench_cmd(args) if args.domain == "mujoco" else atari_bench_cmd(args)
    print(" ".join(cmd), flush=True)
    if args.only_print:
        return 0
    return subprocess.call(cmd, cwd=ROOT)


if __name__ == "__main__":
    sys.exit(main())
