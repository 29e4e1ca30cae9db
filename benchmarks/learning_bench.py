#!/usr/bin/env python3
"""Learning benchmark through the ROS node suite: COMCACT vs DDPG (comcact_node, MuJoCo) and COMPER,
COMPER-F, COMPER-M vs DQN (comper_node, vector tasks with discrete actions such as CartPole-v1).

Each run is `ros2 run comper_agent comcact_node` or `comper_node` (embedded bring-up: sim, memory and
QT trainer nodes in the learner's process, talking over ROS) in its own subprocess with its own
ROS_DOMAIN_ID; at most --parallel runs at a time. Results come from each run's metrics.jsonl
(evaluations: eval_episodes greedy episodes every eval_every steps on a separate environment; the
time split logged at the end of the run). The table gives, per (task, algorithm), the mean over
seeds with a bootstrap 95% confidence interval of the seed means, and how many runs reached
--target at any evaluation; with --baseline, a second table gives each algorithm's difference to that
one, with a bootstrap 95% interval of the difference.

    python benchmarks/learning_bench.py                                   # the MuJoCo protocol (long!)
    python benchmarks/learning_bench.py --tasks InvertedPendulum-v4 --seeds 1 --total-steps 20000
    python benchmarks/learning_bench.py --tasks CartPole-v1 Acrobot-v1 --algorithms comper comper_f comper_m dqn
    python benchmarks/learning_bench.py --tasks Hopper-v4 --total-steps 5000 --eval-every 5000 --tag speed

Writes <out>/<tag>/{results.md, results.json, curves_<task>.png, runs/<run_id>/..., logs/<run_id>.log}.
Ctrl-C or SIGTERM stops the runs in progress as their own Ctrl-C would (final checkpoint and summary, at
most 2 minutes) and reports what finished. Started again with the same --out, --tag and grid, the bench skips
the runs whose last checkpoint is at their budget and continues each one stopped before it from its last
checkpoint (``resume``, with the memory's or replay buffer's contents: checkpoint_replay), so a sweep longer
than a session splits over several; a run killed outright goes on from its last periodic checkpoint (every
5,000 steps), and the evaluations its first session logged past that point are replaced by the second's.
Stable-Baselines3 reference runs cannot resume: one stopped early starts again. --force starts every run afresh.
"""
from __future__ import annotations

import argparse
import json
import os
import random
import shutil
import subprocess
import sys
import time
from pathlib import Path

from bench_args import raise_on_sigterm, resume_status, stop_nodes, stop_runs
from comper_agent.nodes.run_io import MetricsLog

ROOT = Path(__file__).resolve().parents[1]
COMPER_ALGORITHMS = ["comper", "comper_f", "comper_m", "dqn"]
DEFAULT_TASKS = ["Hopper-v4", "Walker2d-v4", "HalfCheetah-v4", "InvertedPendulum-v4", "InvertedDoublePendulum-v4"]


def parse_args(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--tasks", nargs="+", default=DEFAULT_TASKS, help="gymnasium task ids")
    ap.add_argument("--algorithms", nargs="+", default=["comcact", "ddpg"],
                    help="comcact, ddpg: comcact_node (continuous actions) with its default profile (auto: "
                         "fresh_labels_gate for comcact; records of versions before 0.2.0 ran comcact with the thesis "
                         "profile, which is now a variant: NAME=comcact:profile=thesis); comper, comper_f, comper_m, "
                         "dqn: comper_node (discrete actions); sb3_ddpg: Stable-Baselines3 DDPG with default settings, "
                         "same evaluation protocol (benchmarks/sb3_reference.py; SB3 comes with make setup, requirements-extras.lock)")
    ap.add_argument("--variant", action="append", default=[], metavar="NAME=ALGORITHM:PARAM=VALUE[,PARAM=VALUE]",
                    help="a named configuration usable in --algorithms, e.g. "
                         "comcact_restore=comcact:restore_batch=true,label_critic=target (its runs get "
                         "-p algorithm:=ALGORITHM -p PARAM:=VALUE ...; repeatable)")
    ap.add_argument("--target", type=float, default=None,
                    help="a return to count runs that reach it at any evaluation (e.g. 475 for CartPole-v1)")
    ap.add_argument("--seeds", type=int, default=3, help="seeds per (task, algorithm): 0..N-1")
    ap.add_argument("--total-steps", type=int, default=50_000, help="steps per run (thesis: 50,000)")
    ap.add_argument("--eval-every", type=int, default=5_000, help="steps between evaluations (thesis: 5,000)")
    ap.add_argument("--eval-episodes", type=int, default=10, help="episodes per evaluation (thesis: 10)")
    ap.add_argument("--report-steps", type=int, nargs="+", default=[10_000, 25_000, 50_000],
                    help="steps at which the table reports the evaluation return (nearest evaluation at or before)")
    ap.add_argument("--final-evals", type=int, default=3,
                    help="the table's last column: each run's mean over its last this many evaluations on the "
                         "eval_every grid (3: 40,000, 45,000 and 50,000 of a 50,000-step run), less noisy than the "
                         "single evaluation at the end (0: no column)")
    ap.add_argument("--parallel", type=int, default=2, help="runs at a time (the machine has 2 cores)")
    ap.add_argument("--out", default=str(ROOT / "benchmarks" / "results" / "learning"), help="output folder")
    ap.add_argument("--tag", default=time.strftime("%Y%m%d-%H%M%S"), help="sub-folder of --out for this sweep")
    ap.add_argument("--ros-args", nargs=argparse.REMAINDER, default=[],
                    help="extra parameters for every run, e.g. --ros-args -p reduce_every:=1 (must come last)")
    ap.add_argument("--timeout-s", type=float, default=6 * 3600, help="kill a run after this many seconds")
    ap.add_argument("--only", nargs="+", default=[], metavar="RUN_ID",
                    help="run only these runs of the grid (e.g. the ones a broken machine ended early); the report "
                         "still covers every run found in <out>/<tag>")
    ap.add_argument("--force", action="store_true",
                    help="start every run of the grid afresh (its folder is replaced), even one that is done or can "
                         "continue from its checkpoint")
    ap.add_argument("--report-only", action="store_true", help="only rebuild the tables/plots from <out>/<tag>")
    ap.add_argument("--baseline", default=None, metavar="ALGORITHM",
                    help="add a table of each other algorithm's difference to this one (difference of the means over "
                         "seeds, bootstrap 95%% interval with each algorithm's seeds resampled on their own; 'above' or "
                         "'below' only where that interval excludes 0), e.g. --baseline ddpg")
    ap.add_argument("--include", nargs="+", default=[], metavar="RESULTS_JSON",
                    help="results.json files of earlier sweeps (e.g. docs/results/learning/*.json, kept in git): "
                         "their runs join this table and the plots (a sweep split over several sessions or "
                         "machines); runs of this sweep win on the same run id")
    args = ap.parse_args(argv)
    args.variants = parse_variants(args.variant)
    known = ["comcact", "ddpg", "sb3_ddpg", *COMPER_ALGORITHMS, *args.variants]
    bad = [a for a in args.algorithms if a not in known]
    if bad:
        ap.error(f"unknown algorithm(s) {', '.join(bad)}: choose from {', '.join(known)} (or define one with --variant)")
    return args


def parse_variants(specs) -> dict:
    """{name: (base algorithm, [(param, value), ...])} from --variant NAME=ALGORITHM:P=V,P=V."""
    out = {}
    for spec in specs:
        name, sep, rest = spec.partition("=")
        base, _, params = rest.partition(":")
        pairs = [kv.split("=", 1) for kv in params.split(",") if kv]
        if not sep or not name or base not in ("comcact", "ddpg", *COMPER_ALGORITHMS) \
                or any(len(kv) != 2 or not kv[0] for kv in pairs):
            raise SystemExit(f"--variant {spec!r}: expected NAME=ALGORITHM:PARAM=VALUE[,PARAM=VALUE] with ALGORITHM "
                             f"one of comcact, ddpg, {', '.join(COMPER_ALGORITHMS)}")
        out[name] = (base, [(k, v) for k, v in pairs])
    return out


def run_id(alg, task, seed):
    return f"{alg}-{task.replace('/', '_')}-s{seed}"


def run_status(args, base: Path, alg, task, seed) -> str:
    """'done', 'continue' or 'new' for one run of the grid (bench_args.resume_status; a Stable-Baselines3 run is
    done when its final 'timers' record covers the budget, else new: it cannot resume)."""
    d = base / "runs" / run_id(alg, task, seed)
    if alg == "sb3_ddpg":
        timers = MetricsLog.read(d / "metrics.jsonl", "timers", missing_ok=True)
        return "done" if timers and timers[-1].get("steps", 0) >= args.total_steps else "new"
    return resume_status(d, args.total_steps)


def launch(args, base: Path, alg, task, seed, domain, resume: bool = False):
    """Start one run of the grid; ``resume``: continue it from its folder's last checkpoint."""
    rid = run_id(alg, task, seed)
    if alg == "sb3_ddpg":
        cmd = [sys.executable, str(ROOT / "benchmarks" / "sb3_reference.py"), "--env-id", task, "--seed", str(seed),
               "--total-steps", str(args.total_steps), "--eval-every", str(args.eval_every),
               "--eval-episodes", str(args.eval_episodes), "--run-dir", str(base / "runs" / rid)]
        return _spawn(base, rid, cmd, domain, alg, task, seed)
    base_alg, params = args.variants.get(alg, (alg, []))
    node, budget = ("comper_node", "total_frames") if base_alg in COMPER_ALGORITHMS else ("comcact_node", "total_steps")
    cmd = [shutil.which("ros2") or "ros2", "run", "comper_agent", node, "--ros-args",
           "-p", f"algorithm:={base_alg}", "-p", f"env_id:={task}", "-p", f"seed:={seed}",
           "-p", f"{budget}:={args.total_steps}", "-p", f"eval_every:={args.eval_every}",
           "-p", f"eval_episodes:={args.eval_episodes}", "-p", f"runs_root:={base / 'runs'}",
           "-p", f"run_id:={rid}", "-p", "progress_period_s:=30.0"]
    extra = list(args.ros_args)
    if extra and extra[0] == "--ros-args":
        extra = extra[1:]
    cmd += extra
    for k, v in params:
        cmd += ["-p", f"{k}:={v}"]
    if resume:                 # the same parameters as its first session; the checkpoint says where it stopped
        cmd += ["-p", f"resume:={base / 'runs' / rid}"]
    return _spawn(base, rid, cmd, domain, alg, task, seed, resume)


def _spawn(base: Path, rid: str, cmd: list, domain: int, alg, task, seed, resume: bool = False) -> dict:
    env = os.environ.copy()
    env["ROS_DOMAIN_ID"] = str(domain)
    env.setdefault("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")
    env.setdefault("OMP_NUM_THREADS", "1")
    (base / "logs").mkdir(parents=True, exist_ok=True)
    log = open(base / "logs" / f"{rid}.log", "ab" if resume else "wb")
    if not resume:
        shutil.rmtree(base / "runs" / rid, ignore_errors=True)
    p = subprocess.Popen(cmd, stdout=log, stderr=subprocess.STDOUT, env=env, start_new_session=True)
    return {"rid": rid, "proc": p, "log": log, "t0": time.monotonic(), "alg": alg, "task": task, "seed": seed}


DOMAIN_CLAIMS = Path(os.environ.get("TMPDIR", "/tmp")) / "comper-ros-domains"


def resumed_evals(evals: list[dict]) -> list[dict]:
    """A run's evaluation records in step order, as its last session saw them: a session resumed from a checkpoint
    older than evaluations the killed session had logged evaluates those steps again, and its records replace
    them (with the weights the run went on from)."""
    return went_on_with(evals, "step")


def went_on_with(records: list[dict], key: str) -> list[dict]:
    """Records in file order, each dropping the earlier ones whose `key` is not below its own (a resumed session
    logging again what a stopped one had logged)."""
    out: list[dict] = []
    for e in records:
        while out and out[-1][key] >= e[key]:
            out.pop()
        out.append(e)
    return out


def resumed_episodes(episodes: list[dict]) -> list[dict]:
    """A run's episode records of the timeline it went on with: a session resumed from a checkpoint counts episodes
    again from the checkpoint's count, so records the killed session had logged with that index or a later one
    belong to steps that were played again, and are dropped (an episode's end step cannot tell them apart: the
    replayed episodes end later than the dropped ones)."""
    return went_on_with(episodes, "episode")


def run_timers(records: list[dict]) -> dict | None:
    """A run's time split over its sessions (one 'timers' record each; a session killed outright leaves none, and
    its time is not counted): seconds, steps and phases summed, steps/s over the sum; other fields the last's."""
    if len(records) <= 1:
        return records[0] if records else None
    out = dict(records[-1], sessions=len(records))
    out["elapsed_s"] = sum(r["elapsed_s"] for r in records)
    out["steps"] = sum(r["steps"] for r in records)
    out["steps_per_s"] = out["steps"] / max(out["elapsed_s"], 1e-9)
    phases: dict = {}
    for r in records:
        for k, v in (r.get("phases") or {}).items():
            ph = phases.setdefault(k, {"seconds": 0.0, "calls": 0})
            ph["seconds"] += v["seconds"]
            ph["calls"] += v["calls"]
    out["phases"] = phases
    return out


def on_grid(evals, every: int) -> list[tuple[int, float]]:
    """(step, mean return) of each logged evaluation, with the step put on the eval_every grid when it lies
    just past a grid point: an async learner evaluates at the first step count at or past each multiple
    (its actors store in batches), e.g. 25,024 for 25,000. Other steps are kept as logged."""
    out = []
    for e in evals:
        st, k = int(e[0]), int(e[0]) // every * every
        out.append((k if 0 <= st - k < max(1, every // 10) else st, float(e[1])))
    return out


def claim_domain() -> int:
    """A ROS_DOMAIN_ID in 101..231 that no other run on this machine holds (a claim file created with
    O_EXCL; a claim whose process is gone is taken over). Nodes of two runs in one domain have the same
    names and would answer each other's services."""
    DOMAIN_CLAIMS.mkdir(parents=True, exist_ok=True)
    for dom in random.SystemRandom().sample(range(101, 232), k=131):
        path = DOMAIN_CLAIMS / str(dom)
        try:
            fd = os.open(path, os.O_CREAT | os.O_EXCL | os.O_WRONLY)
        except FileExistsError:
            try:
                os.kill(int(path.read_text() or 0), 0)
                continue                      # held by a live process
            except (ProcessLookupError, ValueError):
                path.unlink(missing_ok=True)  # stale: its process is gone
                try:
                    fd = os.open(path, os.O_CREAT | os.O_EXCL | os.O_WRONLY)
                except FileExistsError:
                    continue
            except PermissionError:
                continue
        os.write(fd, str(os.getpid()).encode())
        os.close(fd)
        return dom
    raise RuntimeError(f"no free ROS domain id in 101..231 (claims in {DOMAIN_CLAIMS})")


def release_domain(dom: int) -> None:
    (DOMAIN_CLAIMS / str(dom)).unlink(missing_ok=True)


def run_all(args, base: Path) -> None:
    # seed-major: a sweep stopped early still holds every (task, algorithm) for the first seeds
    jobs = [(a, t, s) for s in range(args.seeds) for t in args.tasks for a in args.algorithms]
    if args.only:
        unknown = set(args.only) - {run_id(*j) for j in jobs}
        if unknown:
            raise SystemExit(f"--only: {', '.join(sorted(unknown))} not in this grid")
        jobs = [j for j in jobs if run_id(*j) in args.only]
    status = {j: "new" if args.force else run_status(args, base, *j) for j in jobs}
    skipped = [run_id(*j) for j in jobs if status[j] == "done"]
    if skipped:
        print(f"[bench] {len(skipped)} run(s) already at their budget, not run again: {', '.join(skipped)}", flush=True)
    jobs = [j for j in jobs if status[j] != "done"]
    print(f"[bench] {len(jobs)} runs ({len(args.tasks)} tasks x {len(args.algorithms)} algorithms x "
          f"{args.seeds} seeds), {args.total_steps} steps each, {args.parallel} at a time; outputs in {base}",
          flush=True)
    running: list[dict] = []
    t_start = time.monotonic()
    try:
        _run_jobs(args, base, jobs, running, status)
    except KeyboardInterrupt:
        stop_runs([r["proc"] for r in running], 120.0)
        for r in running:
            r["log"].close()
            release_domain(r["domain"])
        raise
    print(f"[bench] all runs finished in {time.monotonic() - t_start:.0f} s", flush=True)


def _run_jobs(args, base: Path, jobs: list, running: list, status: dict) -> None:
    done, last_status = 0, 0.0
    while jobs or running:
        while jobs and len(running) < args.parallel:
            a, t, s = jobs.pop(0)
            dom = claim_domain()
            resume = status[(a, t, s)] == "continue"
            r = launch(args, base, a, t, s, dom, resume=resume)
            r["domain"] = dom
            running.append(r)
            print(f"[bench] {'continue' if resume else 'start'} {r['rid']} (ROS_DOMAIN_ID {dom})", flush=True)
        time.sleep(2.0)
        for r in list(running):
            rc = r["proc"].poll()
            if rc is None and time.monotonic() - r["t0"] > args.timeout_s:
                stop_nodes([r["proc"]], 60.0)
                rc = r["proc"].returncode
            if rc is not None:
                r["log"].close()
                release_domain(r["domain"])
                running.remove(r)
                done += 1
                evals = MetricsLog.read(base / "runs" / r["rid"] / "metrics.jsonl", "eval", missing_ok=True)
                last = f"eval {evals[-1]['mean_return']:.1f} at {evals[-1]['step']}" if evals else "no eval"
                print(f"[bench] done {r['rid']} rc {rc} in {time.monotonic() - r['t0']:.0f} s: {last} "
                      f"({done} finished, {len(jobs)} waiting)", flush=True)
        if time.monotonic() - last_status > 60 and running:
            last_status = time.monotonic()
            for r in running:
                prog = MetricsLog.read(base / "runs" / r["rid"] / "metrics.jsonl", "progress", missing_ok=True)
                if prog:
                    print(f"[bench]   {r['rid']}: step {prog[-1]['step']}, {prog[-1]['steps_per_s']:.0f} steps/s",
                          flush=True)


def final_mean(evals, every: int, total: int, k: int) -> float | None:
    """A run's mean evaluation return over the last k grid points up to ``total`` (every one of them
    evaluated), or None if it lacks one (a run ended early)."""
    want = [total // every * every - i * every for i in range(k)]
    got = {st: r for st, r in on_grid(evals, every)}
    if k <= 0 or min(want) < 0 or any(w not in got for w in want):
        return None
    return sum(got[w] for w in want) / k


def at_step(evals, step):
    cands = [e for e in evals if e["step"] <= step]
    return cands[-1] if cands else None


def return_at(evals, step: int, every: int) -> float | None:
    """A run's evaluation return at ``step``: its last evaluation on the grid at or before it, if that one lies
    within the last eval_every steps (None for a run that ended before). Where two evaluations fall on one grid point
    the first counts: comper_node also evaluates once after its budget, when the episode in progress has finished
    (e.g. at 50,248 for a 50,000-frame budget), which is not the evaluation at the budget."""
    first: dict[int, float] = {}
    for st, mr in on_grid(evals, every):
        first.setdefault(st, mr)
    e = at_step([{"step": st, "mean_return": mr} for st, mr in first.items()], step)
    return e["mean_return"] if e is not None and e["step"] >= step - every + 1 else None


def bootstrap_ci(values, n_boot: int = 10_000, seed: int = 0) -> tuple[float, float]:
    """Percentile bootstrap 95% interval of the mean of `values` (resampling the runs)."""
    import numpy as np
    v = np.asarray(values, float)
    if v.size < 2:
        return float(v.mean()), float(v.mean())
    means = resampled_means(v, np.random.default_rng(seed), n_boot)
    return float(np.percentile(means, 2.5)), float(np.percentile(means, 97.5))


def resampled_means(v, rng, n_boot: int):
    """The means of n_boot resamples (with replacement) of the runs' values `v`."""
    return v[rng.integers(0, v.size, size=(n_boot, v.size))].mean(axis=1)


def bootstrap_diff_ci(values, baseline, n_boot: int = 10_000, seed: int = 0) -> tuple[float, float]:
    """Percentile bootstrap 95% interval of mean(values) - mean(baseline). The two groups are independent runs
    (seed k of one algorithm is not paired with seed k of the other), so each group is resampled on its own."""
    import numpy as np
    v, b = np.asarray(values, float), np.asarray(baseline, float)
    if v.size == 0 or b.size == 0:
        raise ValueError("bootstrap_diff_ci needs at least one run in each group")
    rng = np.random.default_rng(seed)
    d = resampled_means(v, rng, n_boot) - resampled_means(b, rng, n_boot)
    return float(np.percentile(d, 2.5)), float(np.percentile(d, 97.5))


def difference(values, baseline) -> dict:
    """One cell of the --baseline table: the difference of the means, its interval, and a verdict that says
    'above' or 'below' only where the interval excludes 0."""
    import numpy as np
    lo, hi = bootstrap_diff_ci(values, baseline)
    verdict = "above" if lo > 0 else "below" if hi < 0 else "not separated"
    return {"diff": float(np.mean(values) - np.mean(baseline)), "ci95": [lo, hi], "verdict": verdict,
            "n": len(values), "n_baseline": len(baseline)}


def difference_cell(d: dict) -> str:
    """One difference() result as the reports print it: '+12.3 [-4.5, +28.0] not separated'."""
    return f"{d['diff']:+.1f} [{d['ci95'][0]:+.1f}, {d['ci95'][1]:+.1f}] {d['verdict']}"


def difference_table(args, table: dict, steps: list) -> tuple[list, dict]:
    """Markdown lines and results of each algorithm's difference to args.baseline, from the main table's per-seed
    values (the same runs, report steps and last-k column)."""
    keys = [str(x) for x in steps] + (["final"] if args.final_evals > 0 else [])
    heads = [f"return @ {x:,}" for x in steps] + ([f"last {args.final_evals} evals"] if args.final_evals > 0 else [])
    lines = [f"Difference to {args.baseline} (this algorithm's mean minus {args.baseline}'s, bootstrap 95% interval "
             "with each algorithm's seeds resampled on their own; above / below only where it excludes 0):", "",
             "| task | algorithm | seeds (this / baseline) | " + " | ".join(heads) + " |",
             "|---|---|---|" + "---|" * len(keys)]
    out = {}
    for t in args.tasks:
        ref = table.get(f"{t}/{args.baseline}")
        if not ref:
            continue
        for a in args.algorithms:
            row = table.get(f"{t}/{a}")
            if a == args.baseline or not row:
                continue
            cells, res = [], {}
            for k in keys:
                if k in row and k in ref:
                    d = res[k] = difference(row[k]["values"], ref[k]["values"])
                    cells.append(difference_cell(d))
                else:
                    cells.append("-")
            if res:
                out[f"{t}/{a}"] = res
                n = next(iter(res.values()))
                lines.append(f"| {t} | {a} | {n['n']} / {n['n_baseline']} | " + " | ".join(cells) + " |")
    return lines, out


MEMORY_FIELDS = ("identities", "transitions_stored", "bytes_used", "evictions", "similarity_hits", "rtm_size",
                 "replay_size", "replay_bytes")


def memory_summary(metrics: Path) -> list[dict]:
    """A run's 'memory' records (one per evaluation) cut to what the budget study reports: step, identities,
    transitions stored, bytes held, evictions (a DDPG run: its replay's size and bytes)."""
    recs = went_on_with(MetricsLog.read(metrics, "memory", missing_ok=True), "step")
    return [{"step": r["step"], **{k: r[k] for k in MEMORY_FIELDS if k in r}} for r in recs]


def report(args, base: Path) -> dict:
    import numpy as np
    results = {"total_steps": args.total_steps, "eval_every": args.eval_every, "eval_episodes": args.eval_episodes,
               "report_steps": args.report_steps,
               "variants": {k: {"algorithm": b, "params": dict(ps)} for k, (b, ps) in args.variants.items()},
               "runs": {}, "table": {}}
    for t in args.tasks:
        for a in args.algorithms:
            for s in range(args.seeds):
                rid = run_id(a, t, s)
                m = base / "runs" / rid / "metrics.jsonl"
                evals = resumed_evals(MetricsLog.read(m, "eval", missing_ok=True))
                timers = run_timers(MetricsLog.read(m, "timers", missing_ok=True))
                results["runs"][rid] = {"task": t, "algorithm": a, "seed": s,
                                        "evals": [(e["step"], e["mean_return"], e["std_return"]) for e in evals],
                                        "timers": timers, "memory": memory_summary(m)}
    tasks, algorithms = list(args.tasks), list(args.algorithms)
    for inc in args.include:
        prev = json.loads(Path(inc).read_text())
        if prev["total_steps"] != args.total_steps or prev["eval_every"] != args.eval_every:
            print(f"[bench] {inc}: {prev['total_steps']} steps / eval every {prev['eval_every']}, not "
                  f"{args.total_steps} / {args.eval_every}: not included", flush=True)
            continue
        for k, v in prev.get("variants", {}).items():
            results["variants"].setdefault(k, v)
        for rid, r in prev["runs"].items():
            if r["evals"] and not (rid in results["runs"] and results["runs"][rid]["evals"]):
                results["runs"][rid] = r
                tasks += [r["task"]] if r["task"] not in tasks else []
                algorithms += [r["algorithm"]] if r["algorithm"] not in algorithms else []
    args.tasks, args.algorithms = tasks, algorithms
    steps = [x for x in args.report_steps if x <= args.total_steps] or [args.total_steps]
    reached_col = args.target is not None
    k_final = args.final_evals
    final_head = (f" | last {k_final} evals ({args.total_steps - (k_final - 1) * args.eval_every:,}-"
                  f"{args.total_steps:,}) [95% CI]" if k_final > 0 else "")
    lines = [f"| task | algorithm | seeds | " + " | ".join(f"return @ {x:,} [95% CI]" for x in steps)
             + final_head + (f" | reached {args.target:g} | best eval" if reached_col else "") + " | steps/s |",
             "|---|---|---|" + "---|" * len(steps) + ("---|" if k_final > 0 else "")
             + ("---|---|" if reached_col else "") + "---|"]
    for t in args.tasks:
        for a in args.algorithms:
            runs = [r for r in results["runs"].values() if r["task"] == t and r["algorithm"] == a and r["evals"]]
            cells = []
            row = {}
            for x in steps:
                vals = [v for v in (return_at(r["evals"], x, args.eval_every) for r in runs) if v is not None]
                if vals:
                    lo, hi = bootstrap_ci(vals)
                    cells.append(f"{np.mean(vals):.1f} [{lo:.1f}, {hi:.1f}] (n={len(vals)})")
                    row[str(x)] = {"mean": float(np.mean(vals)), "std": float(np.std(vals)), "n": len(vals),
                                   "ci95": [lo, hi], "values": [float(v) for v in vals]}
                else:
                    cells.append("-")
            if k_final > 0:
                vals = [v for v in (final_mean(r["evals"], args.eval_every, args.total_steps, k_final)
                                    for r in runs) if v is not None]
                if vals:
                    lo, hi = bootstrap_ci(vals)
                    cells.append(f"{np.mean(vals):.1f} [{lo:.1f}, {hi:.1f}] (n={len(vals)})")
                    row["final"] = {"evals": k_final, "mean": float(np.mean(vals)), "n": len(vals),
                                    "ci95": [lo, hi], "values": vals}
                else:
                    cells.append("-")
            if reached_col:
                best = [max(e[1] for e in r["evals"]) for r in runs]
                row["reached"] = int(sum(b >= args.target for b in best))
                row["best"] = [float(b) for b in best]
                cells.append(f"{row['reached']}/{len(runs)}")
                cells.append(", ".join(f"{b:.0f}" for b in best) or "-")
            rates = [r["timers"]["steps_per_s"] for r in runs if r["timers"]]
            rate = f"{np.mean(rates):.1f}" if rates else "-"
            row["steps_per_s"] = float(np.mean(rates)) if rates else None
            results["table"][f"{t}/{a}"] = row
            lines.append(f"| {t} | {a} | {len(runs)} | " + " | ".join(cells) + f" | {rate} |")
    if args.baseline:
        if args.baseline not in args.algorithms:
            print(f"[bench] --baseline {args.baseline}: not among the algorithms reported; no difference table",
                  flush=True)
        else:
            diff_lines, results["differences"] = difference_table(args, results["table"], steps)
            lines += ["", *diff_lines]
    md = ["# Learning benchmark", "",
          f"{args.total_steps:,} steps per run, evaluation every {args.eval_every:,} steps "
          f"({args.eval_episodes} greedy episodes), mean over seeds of the per-run mean evaluation return with "
          "a bootstrap 95% confidence interval of that mean (10,000 resamples of the seeds; with 3 seeds it "
          "spans the seeds' range at most); last k evals: the same statistic of each run's mean over its last k "
          "evaluations (--final-evals); steps/s = the whole run including evaluations (sb3_ddpg: "
          "Stable-Baselines3 DDPG, default settings, in-process gymnasium env, no ROS).", "",
          *[f"- {k}: {v['algorithm']} with " + ", ".join(f"{pk}:={pv}" for pk, pv in v["params"].items())
            for k, v in results["variants"].items()], "", *lines, "",
          "Time split per run (seconds; phases measured in the learner node):", ""]
    for rid, r in results["runs"].items():
        if r["timers"]:
            ph = r["timers"]["phases"]
            md.append(f"- {rid}: {r['timers']['elapsed_s']:.0f} s, {r['timers']['steps_per_s']:.1f} steps/s; "
                      + ", ".join(f"{k} {v['seconds']:.1f}" for k, v in sorted(ph.items(), key=lambda kv: -kv[1]['seconds']))
                      + f"; ROS round trip {r['timers']['ros_round_trip_ms']:.2f} ms x {r['timers']['service_calls']} calls")
    (base / "results.md").write_text("\n".join(md) + "\n")
    (base / "results.json").write_text(json.dumps(results, indent=1))
    try:
        import matplotlib
        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
        for t in args.tasks:
            fig, ax = plt.subplots(figsize=(6, 4))
            for a in args.algorithms:
                runs = [r for r in results["runs"].values() if r["task"] == t and r["algorithm"] == a and r["evals"]]
                if not runs:
                    continue
                # the evaluations on the eval_every grid (comper_node adds one at the run's last step)
                grid = [[e for e in on_grid(r["evals"], args.eval_every) if e[0] % args.eval_every == 0] for r in runs]
                n = min(len(g) for g in grid)
                st = np.array([e[0] for e in grid[0][:n]])
                vals = np.array([[e[1] for e in g[:n]] for g in grid])
                ax.plot(st, vals.mean(0), label=f"{a} (n={len(runs)})")
                ax.fill_between(st, vals.min(0), vals.max(0), alpha=0.2)
            ax.set_title(f"{t}: mean over seeds, band = min..max")
            ax.set_xlabel("environment steps")
            ax.set_ylabel("evaluation return")
            ax.legend()
            fig.tight_layout()
            fig.savefig(base / f"curves_{t.replace('/', '_')}.png", dpi=100)
            plt.close(fig)
    except Exception as exc:
        print(f"[bench] plots skipped: {exc}", flush=True)
    print("\n".join(lines), flush=True)
    print(f"[bench] wrote {base / 'results.md'}, {base / 'results.json'} and curves_*.png", flush=True)
    return results


def main(argv=None) -> int:
    args = parse_args(argv)
    base = Path(args.out) / args.tag
    base.mkdir(parents=True, exist_ok=True)
    if not args.report_only:
        raise_on_sigterm()
        try:
            run_all(args, base)
        except KeyboardInterrupt:
            print("[bench] interrupted: reporting what finished", flush=True)
    report(args, base)
    return 0


if __name__ == "__main__":
    sys.exit(main())
