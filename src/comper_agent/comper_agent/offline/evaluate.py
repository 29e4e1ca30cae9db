"""evaluate: offline evaluation of recorded training runs (rosbag2 bags from recorder_node).

    ros2 run comper_agent evaluate runs/hopper-s0 runs/hopper-s1 --out reports/hopper
    ros2 run comper_agent evaluate runs/hopper-s0/bag --checkpoint runs/hopper-s0/checkpoint.pt

Writes into --out: report.md (tables), summary.json (everything, exact float64 returns),
episodes.csv (one row per training episode) and PNG plots (learning curves per algorithm and
task, evaluation curves mean +- std across runs, Q estimate vs Monte-Carlo return with
--checkpoint). Summaries follow the thesis (method.md section 5): mean of the last 10 training
episodes (last 3 for runs with under 25 episodes), mean of the last 5 (3) episodes at the end of
each tercile of the budget, and the evaluation points; mean +- std (population) across runs
grouped by algorithm and task. Returns are the EpisodeSummary messages' float64 values (what the
agent printed), cross-checked against the returns summed from the recorded transitions.

A bag that cannot be read (truncated by a killed recorder, no metadata.yaml, a damaged file) or
that holds no episodes is reported in one line naming the bag and what to run; ``--repair``
first rebuilds each bag's metadata.yaml from its complete storage files
(``comper_agent.recording.bags.repair_bag``: a partial file is moved to ``<bag>/.open/``, untouched),
then evaluates. ``--repair`` with ``--out -`` only repairs.
"""
from __future__ import annotations

import argparse
import csv
import json
import math
import re
import sys
import time
from pathlib import Path

import numpy as np

from comper_agent.offline import runs as offline

from comper_agent.offline import value_checks

__all__ = ["main", "evaluate"]


def _slug(s: str) -> str:
    return re.sub(r"[^A-Za-z0-9_.-]+", "_", s).strip("_") or "x"


def _fmt(x, digits: int = 2) -> str:
    if x is None or (isinstance(x, float) and math.isnan(x)):
        return "-"
    return f"{x:.{digits}f}"


def _ms(d: dict, digits: int = 2) -> str:
    if not d or d.get("mean") is None:
        return "-"
    return f"{d['mean']:.{digits}f} +- {d['std']:.{digits}f} (n={d['n']})"


def _clean(o):
    """JSON-safe copy: NaN -> None, numpy scalars -> Python, drop private keys."""
    if isinstance(o, dict):
        return {k: _clean(v) for k, v in o.items() if not str(k).startswith("_")}
    if isinstance(o, (list, tuple)):
        return [_clean(v) for v in o]
    if isinstance(o, np.generic):
        o = o.item()
    if isinstance(o, float) and math.isnan(o):
        return None
    return o


def _plots(out: Path, runs: dict, summaries: list, groups: list, q_results: dict) -> list[str]:
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    files = []
    for g in groups:
        fig, (ax1, ax2) = plt.subplots(1, 2, figsize=(12, 4.2))
        for rid in g["runs"]:
            s = next(x for x in summaries if x["run_id"] == rid)
            xs = [e["global_frames"] or e["global_step"] for e in s["episodes"]]
            ys = [e["return"] for e in s["episodes"]]
            line, = ax1.plot(xs, ys, lw=0.6, alpha=0.5)
            if len(ys) >= 5:
                w = min(10, len(ys))
                ax1.plot(xs[w - 1:], np.convolve(ys, np.ones(w) / w, mode="valid"), color=line.get_color(),
                         lw=1.6, label=f"{rid} (mean of {w})")
            ev = s["eval_points"]
            if ev:
                ax2.errorbar([p["global_step"] for p in ev], [p["mean"] for p in ev],
                             yerr=[p["std"] for p in ev], marker="o", ms=3, capsize=2, lw=0.8, alpha=0.6, label=rid)
        curve = g["eval_curve"]
        if curve:
            x = np.array([c["global_step"] for c in curve])
            m = np.array([c["mean"] for c in curve])
            sd = np.array([c["std"] for c in curve])
            ax2.plot(x, m, color="k", lw=2, label="mean across runs")
            ax2.fill_between(x, m - sd, m + sd, color="k", alpha=0.12)
        ax1.set(title=f"{g['algorithm']} on {g['env_id']}: training episodes", xlabel="frames (steps)", ylabel="return")
        ax2.set(title="evaluation (mean +- std)", xlabel="training step", ylabel="return")
        for ax in (ax1, ax2):
            ax.grid(alpha=0.3)
            if ax.get_legend_handles_labels()[0]:
                ax.legend(fontsize=7)
        fig.tight_layout()
        name = f"curves_{_slug(g['algorithm'])}_{_slug(g['env_id'])}.png"
        fig.savefig(out / name, dpi=110)
        plt.close(fig)
        files.append(name)
    envs = sorted({g["env_id"] for g in groups})
    for env in envs:
        gs = [g for g in groups if g["env_id"] == env and g["eval_curve"]]
        if len(gs) < 2:
            continue
        fig, ax = plt.subplots(figsize=(6.5, 4.2))
        for g in gs:
            x = np.array([c["global_step"] for c in g["eval_curve"]])
            m = np.array([c["mean"] for c in g["eval_curve"]])
            sd = np.array([c["std"] for c in g["eval_curve"]])
            ax.plot(x, m, lw=1.8, label=f"{g['algorithm']} ({len(g['runs'])} runs)")
            ax.fill_between(x, m - sd, m + sd, alpha=0.15)
        ax.set(title=f"{env}: evaluation return across runs", xlabel="training step", ylabel="return")
        ax.grid(alpha=0.3)
        ax.legend()
        fig.tight_layout()
        name = f"eval_{_slug(env)}.png"
        fig.savefig(out / name, dpi=110)
        plt.close(fig)
        files.append(name)
    for rid, res in q_results.items():
        qm = res.get("q_vs_mc", {})
        if "_q" not in qm:
            continue
        fig, ax = plt.subplots(figsize=(5, 5))
        q, g = qm["_q"], qm["_g"]
        sel = np.random.default_rng(0).choice(q.size, min(q.size, 20000), replace=False)
        ax.scatter(g[sel], q[sel], s=2, alpha=0.3)
        lo, hi = float(min(g.min(), q.min())), float(max(g.max(), q.max()))
        ax.plot([lo, hi], [lo, hi], "k--", lw=1)
        ax.set(title=f"{rid}: Q(s,a) vs MC return\nbias {qm['bias']:.2f}, corr {qm['corr']:.3f}",
               xlabel=f"discounted MC return (gamma {qm['gamma']})", ylabel="critic Q(s, a)")
        ax.grid(alpha=0.3)
        fig.tight_layout()
        name = f"q_vs_mc_{_slug(rid)}.png"
        fig.savefig(out / name, dpi=110)
        plt.close(fig)
        files.append(name)
    return files


def _report(out: Path, args, summaries: list, groups: list, q_results: dict, plots: list, seconds: float) -> str:
    L = ["# Offline evaluation report", "",
         f"Bags: {', '.join(sorted({b for s in summaries for b in s['bags']}))}", "",
         "Summaries (method.md 5): **final** = mean of the last 10 training episodes (last 3 for runs "
         "with under 25 episodes); **T1/T2/T3** = mean of the last 5 (3) episodes ended by the end of "
         "each third of the budget; **eval** = the last evaluation point (mean of its episodes). "
         "Across runs: mean +- population std.", ""]
    L += ["## By algorithm and task", "",
          "| algorithm | task | runs | final | T1 | T2 | T3 | final eval |", "|---|---|---|---|---|---|---|---|"]
    for g in groups:
        L.append(f"| {g['algorithm'] or '?'} | {g['env_id'] or '?'} | {len(g['runs'])} | {_ms(g['final'])} | "
                 + " | ".join(_ms(t) for t in g["terciles"]) + f" | {_ms(g['final_eval'])} |")
    for g in groups:
        if g["eval_curve"]:
            L += ["", f"### Evaluation points: {g['algorithm']} on {g['env_id']}", "",
                  "| step | mean across runs | std | runs |", "|---|---|---|---|"]
            L += [f"| {c['global_step']} | {_fmt(c['mean'])} | {_fmt(c['std'])} | {c['n']} |" for c in g["eval_curve"]]
    L += ["", "## Runs", "",
          "| run | algorithm | task | episodes | steps | final (rule) | T1 | T2 | T3 | final eval | transitions | cross-check |",
          "|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for s in summaries:
        cc = s["cross_check"]
        ccs = (f"{cc['checked']} eps, max diff {cc['max_abs_diff']:.2e}, {len(cc['mismatches'])} mismatch"
               if cc["checked"] else "no transitions")
        L.append(f"| {s['run_id']} | {s['algorithm']} | {s['env_id']} | {s['train_episodes']} | {s['global_steps']} | "
                 f"{_fmt(s['final']['mean'])} ({s['final']['rule']}) | "
                 + " | ".join(_fmt(t["mean"]) for t in s["terciles"])
                 + f" | {_fmt(s['final_eval'])} | {s['transitions']} | {ccs} |")
    for s in summaries:
        if s["warnings"]:
            L += ["", f"Warnings for {s['run_id']}: " + "; ".join(s["warnings"])]
    if q_results:
        L += ["", "## Checkpoint value estimates", "", f"Checkpoint: `{args.checkpoint}` (gamma {args.gamma})", "",
              "| run | transitions | bias mean(Q - G) | RMSE | corr | mean Q(s0,a0) | mean G0 | FQE V(pi) | critic V(pi) | FQE updates |",
              "|---|---|---|---|---|---|---|---|---|---|"]
        for rid, r in q_results.items():
            q, f = r.get("q_vs_mc", {}), r.get("fqe", {})
            L.append(f"| {rid} | {q.get('n', 0)} | {_fmt(q.get('bias'), 3)} | {_fmt(q.get('rmse'), 3)} | "
                     f"{_fmt(q.get('corr'), 3)} | {_fmt(q.get('initial_mean_q'))} | {_fmt(q.get('initial_mean_mc'))} | "
                     f"{_fmt(f.get('fqe_value'))} | {_fmt(f.get('critic_value'))} | {f.get('updates', f.get('skipped', '-'))} |")
        L += ["", "Q is the checkpoint's critic on the logged (state, action); G the discounted return the "
              "logged (exploring) behaviour obtained from there, within complete episodes (truncated "
              "episodes end the sum: G underestimates near a time limit). FQE fits Q_pi of the "
              "checkpoint's greedy policy on the logged transitions and reports its value on the "
              "episodes' initial states."]
    if plots:
        L += ["", "## Plots", ""] + [f"![{p}]({p})" for p in plots]
    L += ["", "## Training episodes (returns exactly as published)", ""]
    for s in summaries:
        L += [f"### {s['run_id']}", "",
              "| episode | global step | length | return | terminated | truncated |", "|---|---|---|---|---|---|"]
        L += [f"| {e['episode_id']} | {e['global_step']} | {e['length']} | {e['return']!r} | "
              f"{e['terminated']} | {e['truncated']} |" for e in s["episodes"]]
        L.append("")
    L += [f"_Generated by `evaluate` in {seconds:.2f} s._", ""]
    text = "\n".join(L)
    (out / "report.md").write_text(text)
    return text


class BagError(ValueError):
    """A bag that cannot be evaluated; the message names it and what to run."""


_STORAGE_SUFFIXES = (".mcap", ".db3")


def _storage_dirs(paths) -> list[Path]:
    """Directories holding rosbag2 storage files (bags, with or without metadata.yaml)."""
    out, seen = [], set()
    for p in map(Path, paths):
        if not p.exists():
            raise FileNotFoundError(f"{p} does not exist")
        files = [p] if p.is_file() else [f for f in sorted(p.rglob("*")) if f.suffix in _STORAGE_SUFFIXES]
        for f in files:
            d = f.parent
            if ".open" in d.parts or d.resolve() in seen:
                continue
            seen.add(d.resolve())
            out.append(d)
    return out


def _repair_hint(bag) -> str:
    return (f"run `ros2 run comper_agent evaluate --repair {bag} --out -` (rebuilds metadata.yaml from the "
            f"complete storage files; a partial file is moved to {Path(bag) / '.open'}/, untouched), then "
            "evaluate again")


def repair(paths) -> list[dict]:
    """repair_bag on every bag directory under paths; one result dict per bag (with 'bag')."""
    from comper_agent.recording.bags import repair_bag
    dirs = _storage_dirs(paths)
    if not dirs:
        raise BagError(f"no rosbag2 storage files (.mcap, .db3) under {', '.join(map(str, paths))}")
    return [{"bag": str(d), **repair_bag(d)} for d in dirs]


def _corrupt_file(bag: Path):
    """The first MCAP file of `bag` whose chunk CRC check fails (bytes changed inside it), else None."""
    from comper_agent.recording.bags import check_mcap_file
    for f in sorted(bag.glob("*.mcap")):
        chk = check_mcap_file(f)
        if chk.damage == "crc":
            return chk
    return None


def _check_readable(paths) -> None:
    """Name the first bag that does not open or read to the end, or a bag without metadata.

    A bag with a chunk whose CRC no longer matches gets its own line (file, byte offset, bag_repair);
    a truncated one the repair hint."""
    from rosbags.rosbag2 import Reader
    try:
        bags = offline.find_bags(paths)
    except FileNotFoundError as exc:
        loose = [d for d in _storage_dirs(paths) if not (d / "metadata.yaml").is_file()]
        if loose:
            raise BagError(f"{loose[0]} holds bag files but no metadata.yaml (the recorder did not close "
                           f"the bag); {_repair_hint(loose[0])}") from None
        raise BagError(str(exc)) from None
    for bag in bags:
        bad = _corrupt_file(bag)
        if bad is not None:
            raise BagError(f"bag {bag} is corrupt: {bad.path.name} at byte {bad.offset}: a chunk fails its CRC32 "
                           f"check ({bad.detail}), so bytes changed after it was written; run `ros2 run "
                           f"comper_agent bag_repair {bag}` (sets {bad.path.name} aside in {Path(bag) / '.open'}/, "
                           "the bag's other files stay readable), then evaluate again")
        try:
            with Reader(bag) as r:
                for _ in r.messages():
                    pass
        except Exception as exc:  # noqa: BLE001 - any reader failure: name the bag
            raise BagError(f"cannot read bag {bag}: {type(exc).__name__}: {str(exc).rstrip('.')}. The bag is "
                           f"truncated or damaged (e.g. the recorder was killed while writing); "
                           f"{_repair_hint(bag)}") from None


def evaluate(paths, out, *, checkpoint=None, gamma: float = 0.99, fqe_updates: int = 2000,
             budget: float | None = None, plots: bool = True, algorithm: str | None = None, threads: int = 1,
             args=None) -> dict:
    t0 = time.perf_counter()
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    try:
        runs = offline.read_runs(paths)
    except Exception:  # noqa: BLE001 - find which bag and say what to run, else the original error
        _check_readable(paths)
        raise
    if not any(r.episodes for r in runs.values()):
        raise BagError(f"the bags under {', '.join(map(str, paths))} hold no EpisodeSummary messages "
                       f"({len(runs)} runs with other messages): nothing to evaluate. Was the recorder "
                       "subscribed to the agent's ~/episodes topic (docs/recording.md)?")
    if algorithm:
        for r in runs.values():
            r.algorithm = algorithm
    t_read = time.perf_counter() - t0
    summaries = [offline.run_summary(r, budget=budget) for r in sorted(runs.values(), key=lambda r: r.run_id)]
    groups = offline.group_summaries(summaries)
    q_results = {}
    if checkpoint:
        from comper_agent.core.networks import configure_torch
        configure_torch(threads)   # small networks: one thread is fastest, and robust on a busy machine
        policy = value_checks.load_policy(checkpoint)
        for rid, r in sorted(runs.items()):
            if r.transitions is None or len(r.transitions) == 0:
                continue
            res = {"q_vs_mc": value_checks.q_vs_mc(policy, r.transitions, gamma)}
            if fqe_updates > 0:
                res["fqe"] = value_checks.fitted_q_evaluation(policy, r.transitions, gamma=gamma, updates=fqe_updates)
            q_results[rid] = res
    plot_files = _plots(out, runs, summaries, groups, q_results) if plots else []
    with open(out / "episodes.csv", "w", newline="") as f:
        w = csv.writer(f)
        w.writerow(["run_id", "algorithm", "env_id", "episode_id", "global_step", "global_frames", "length",
                    "return", "terminated", "truncated", "wall_time_s"])
        for s in summaries:
            for e in s["episodes"]:
                w.writerow([s["run_id"], s["algorithm"], s["env_id"], e["episode_id"], e["global_step"],
                            e["global_frames"], e["length"], repr(e["return"]), e["terminated"], e["truncated"],
                            e["wall_time_s"]])
    seconds = time.perf_counter() - t0
    summary = {"runs": summaries, "groups": groups, "checkpoint": str(checkpoint) if checkpoint else None,
               "q_evaluation": q_results, "plots": plot_files,
               "timing_s": {"read": t_read, "total": seconds}}
    (out / "summary.json").write_text(json.dumps(_clean(summary), indent=1))
    ns = argparse.Namespace(checkpoint=checkpoint, gamma=gamma) if args is None else args
    _report(out, ns, summaries, groups, q_results, plot_files, time.perf_counter() - t0)
    return summary


def repair_command(paths, prog: str) -> int:
    """Repair each bag (``repair``) and print a line per bag; one error line and 1 when a path cannot be repaired."""
    try:
        results = repair(paths)
    except (FileNotFoundError, ValueError, OSError) as exc:
        print(f"{prog}: {exc}", file=sys.stderr)
        return 1
    for r in results:
        aside = ", ".join(f"{n} ({r['reasons'].get(n, 'unreadable')})" for n in r["skipped"])
        print(f"repaired {r['bag']}: {len(r['files'])} files, {r['messages']} messages"
              + (f"; set aside in .open/: {aside}" if aside else ""))
    return 0


def main(argv=None) -> int:
    p = argparse.ArgumentParser(prog="ros2 run comper_agent evaluate", description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("paths", nargs="+", help="bag directories or run directories (searched for bags)")
    p.add_argument("--out", default="eval_report", help="output folder (default: eval_report)")
    p.add_argument("--checkpoint", help="COMCACT/DDPG (actor+critic) or COMPER/DQN (q) checkpoint from "
                                        "comper_agent.core.checkpoint: Q vs Monte-Carlo returns and FQE")
    p.add_argument("--gamma", type=float, default=0.99, help="discount of the MC returns and FQE (default 0.99)")
    p.add_argument("--fqe-updates", type=int, default=2000, help="FQE gradient updates (0 = no FQE; default 2000)")
    p.add_argument("--budget", type=float, default=None,
                   help="frame (step) budget for the terciles (default: the last episode's frame count)")
    p.add_argument("--algorithm", help="override the algorithm label of every run")
    p.add_argument("--threads", type=int, default=1, help="torch threads for --checkpoint (default 1)")
    p.add_argument("--no-plots", action="store_true", help="skip the PNG plots")
    p.add_argument("--repair", action="store_true",
                   help="first rebuild each bag's metadata.yaml from its complete storage files (a bag whose "
                        "recorder was killed); the partial file is moved to <bag>/.open/. With --out -: "
                        "repair only")
    args = p.parse_args(sys.argv[1:] if argv is None else argv)
    if args.repair:
        rc = repair_command(args.paths, "evaluate --repair")
        if rc or args.out == "-":
            return rc
    elif args.out == "-":
        p.error("--out - (no report) is only meaningful with --repair")
    try:
        s = evaluate(args.paths, args.out, checkpoint=args.checkpoint, gamma=args.gamma,
                     fqe_updates=args.fqe_updates, budget=args.budget, plots=not args.no_plots,
                     algorithm=args.algorithm, threads=args.threads, args=args)
    except (FileNotFoundError, ValueError) as exc:
        print(f"evaluate: {exc}", file=sys.stderr)
        return 1
    for r in s["runs"]:
        cc = r["cross_check"]
        print(f"{r['run_id']}: {r['algorithm']} {r['env_id']}: {r['train_episodes']} episodes, final "
              f"{_fmt(r['final']['mean'])} ({r['final']['rule']}), terciles "
              f"{', '.join(_fmt(t['mean']) for t in r['terciles'])}, final eval {_fmt(r['final_eval'])}; "
              f"cross-check {cc['checked']} episodes, {len(cc['mismatches'])} mismatches")
    print(f"report: {Path(args.out) / 'report.md'} ({s['timing_s']['total']:.2f} s)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
