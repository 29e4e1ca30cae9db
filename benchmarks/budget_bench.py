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
    python benchmarks/budget_bench.py --domain mujoco --seeds 1 --only-print   # the commands, nothing run

Runs go through benchmarks/learning_bench.py (MuJoCo; resumable: started again with the same --tag it skips
finished runs and continues stopped ones). The budget report (table, plot) is ``--report``.
"""
from __future__ import annotations

import argparse
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]

#: (tasks, steps, budgets) per domain: budgets are ~1/4 and ~1/10 of the run's transitions
DOMAINS = {"mujoco": (["Hopper-v4", "HalfCheetah-v4"], 50_000, [12_500, 5_000])}
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


def variants(budgets: list[int]) -> dict[str, list[tuple[str, str]]]:
    out = {"full": []}
    for b in budgets:
        for m in MEMORIES:
            out[f"{m}-{b}"] = memory_params(m, b)
    return out


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


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--domain", choices=sorted(DOMAINS), default="mujoco")
    ap.add_argument("--seeds", type=int, default=5, help="seeds 0..N-1 (protocol: 5 on MuJoCo)")
    ap.add_argument("--parallel", type=int, default=2)
    ap.add_argument("--tag", default="budget-mujoco", help="learning_bench's sweep folder")
    ap.add_argument("--out", default="", help="learning_bench's --out (default: its own)")
    ap.add_argument("--report-only", action="store_true", help="learning_bench's tables from the runs so far")
    ap.add_argument("--only-print", action="store_true", help="print the command, run nothing")
    args = ap.parse_args(argv)
    cmd = learning_bench_cmd(args)
    print(" ".join(cmd), flush=True)
    if args.only_print:
        return 0
    return subprocess.call(cmd, cwd=ROOT)


if __name__ == "__main__":
    sys.exit(main())
