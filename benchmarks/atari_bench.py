#!/usr/bin/env python3
"""COMPER / COMPER-F / COMPER-M / DQN on Atari through the ROS node suite (thesis chapters 5 and 7).

Each run is one ``ros2 run comper_agent comper_node`` subprocess (embedded bring-up, its own
ROS_DOMAIN_ID so parallel runs never answer each other's services), at most ``--parallel`` (2) at a
time. A run stopped before its budget (Ctrl-C, a session's end: summary.json says complete false, or
none yet) continues from its last checkpoint with ``resume`` when the bench is started again with the
same arguments, memory or replay contents included (checkpoint_replay); a checkpoint without them is
not continued (the run would go on from an empty memory): remove the run folder to start it again.
When all runs are done (or with ``--report-only`` on an existing --out folder) it writes the following, for
the games of ``--games`` and the variants of ``--variants`` only (this --out's runs and the included ones):

* ``<out>/table.md`` + ``<out>/table.json``: per game and variant, the mean across seeds (with a
  bootstrap 95% confidence interval of that mean) of the run's mean of the last 10 training episodes
  (3 for runs with fewer than 25 episodes) and of the three terciles (mean of the last 5 (or 3)
  episodes ended by each third of the 100,000-frame budget; recomputed here from every run's episode
  returns and frames with comper_agent.core.protocol, so runs merged with --include use one
  definition whatever their summary.json says), the thesis's Tables 23/25/30 layout, plus
  frames, episodes, wall time and steps/s; with ``--reference`` (atari_constant_actions.py's JSON)
  the random-play (mean [bootstrap 95% CI over its episodes]) and best-constant-action rows of each game, and a
  table of each variant's difference to random play with its bootstrap 95% interval (the variant's seeds and
  random play's episodes each resampled on their own; "above" only where the interval excludes 0; also in
  table.json as ``vs_random``): a run's figure is tested against random play's measured spread, not against a
  point; with ``--policy``
  (atari_policy_check.py's JSON) how many runs' final greedy action is the initial network's in
  every state, and the distinct greedy actions per run;
* ``<out>/runs.json``: the per-run figures (small; keep it in git and pass it to ``--include`` to
  merge a sweep split over several sessions or machines: runs of this --out win on the same id);
* ``<out>/curve_<game>.png``: training episode returns against frames, one line per variant
  (mean over seeds on a common frame grid, band = min..max; a run's line ends at the frames it has played,
  so a run still under way, "unfinished" in the legend and in the table's seeds cell, is not drawn further);
* ``<out>/memory_<game>.png`` + ``memory.json``: identities, TM sets, RTM size and the mean size of
  the sampled similar-transition sets over frames (comper_node's ``memory`` records).

    python benchmarks/atari_bench.py --games Freeway --variants comper --seeds 0 --out benchmarks/out/atari
    python benchmarks/atari_bench.py                       # 5 games x 4 variants x 3 seeds (long)
    python benchmarks/atari_bench.py --out benchmarks/out/atari --report-only --games Freeway Asterix Seaquest \
        --variants comper dqn comper_n10 --variant comper_n10=comper:n_step=10 \
        --include docs/results/atari/data-efficient-runs.json --reference docs/results/atari/constant-actions.json
"""
from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
import warnings
from pathlib import Path

from comper_agent.core.protocol import protocol_summary
from comper_agent.nodes.run_io import MetricsLog
from learning_bench import claim_domain, parse_variants, release_domain   # one claim registry for every run
from bench_args import raise_on_sigterm, resume_status, stop_runs

import numpy as np

GAMES = ["Freeway", "Asterix", "Seaquest", "SpaceInvaders", "BeamRider"]
VARIANTS = ["comper", "comper_f", "comper_m", "dqn"]


def run_id(game: str, variant: str, seed: int) -> str:
    return f"{variant}-{game}-s{seed}"


def run_status(out: Path, rid: str) -> str:
    """'done' (summary.json with complete true), else bench_args.resume_status of its folder: 'continue' (stopped
    before its budget, with a checkpoint that holds its memory / replay contents) or 'new' (no checkpoint);
    ValueError for a stopped run whose checkpoint lacks them."""
    d = out / "runs" / rid
    if (d / "summary.json").exists() and json.loads((d / "summary.json").read_text()).get("complete"):
        return "done"
    return resume_status(d)


def launch(args, game: str, variant: str, seed: int, domain: int, resume: bool = False) -> subprocess.Popen:
    rid = run_id(game, variant, seed)
    log = open(Path(args.out) / "logs" / f"{rid}.log", "ab" if resume else "wb")
    base, params = args.named.get(variant, (variant, []))
    cmd = ["ros2", "run", "comper_agent", "comper_node", "--ros-args",
           "-p", f"algorithm:={base}", "-p", f"env_id:=ALE/{game}-v5", "-p", f"seed:={seed}",
           "-p", f"total_frames:={args.frames}", "-p", f"runs_root:={Path(args.out) / 'runs'}",
           "-p", f"run_id:={rid}", "-p", f"progress_period_s:={args.progress_period}",
           "-p", "tensorboard:=false"]
    if args.frame_stack and base != "dqn":
        cmd += ["-p", f"frame_stack:={args.frame_stack}"]
    if args.max_steps:
        cmd += ["-p", f"max_steps:={args.max_steps}"]
    for extra in args.ros_arg:
        cmd += ["-p", extra]
    for name, value in params:               # a named variant's own parameters come last, so they win
        cmd += ["-p", f"{name}:={value}"]
    if resume:                               # the same parameters as the first session, from its checkpoint
        cmd += ["-p", f"resume:={Path(args.out) / 'runs' / rid}"]
    env = dict(os.environ, ROS_DOMAIN_ID=str(domain), ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST",
               OMP_NUM_THREADS="1")
    print(f"[bench] {'continue' if resume else 'start'} {rid} (ROS_DOMAIN_ID {domain}): {' '.join(cmd)}", flush=True)
    p = subprocess.Popen(cmd, stdout=log, stderr=subprocess.STDOUT, env=env, start_new_session=True)
    p.rid, p.t0, p.logf = rid, time.monotonic(), log
    return p


def progress_of(args, rid: str) -> str:
    recs = MetricsLog.read(Path(args.out) / "runs" / rid / "metrics.jsonl", "progress", missing_ok=True)
    if not recs:
        return "starting"
    r = recs[-1]
    return f"frames {r.get('frames', 0)}/{args.frames}, {r.get('steps_per_s') or 0:.1f} steps/s, episodes {r.get('episodes')}"


def run_all(args) -> None:
    out = Path(args.out)
    (out / "logs").mkdir(parents=True, exist_ok=True)
    status = {(g, v, s): "new" if args.force else run_status(out, run_id(g, v, s))
              for g in args.games for v in args.variants for s in args.seeds}
    todo = [key for key, st in status.items() if st != "done"]
    print(f"[bench] {len(todo)} runs to do, {args.parallel} at a time, {args.frames} frames each", flush=True)
    running: list[subprocess.Popen] = []
    try:
        _run_queue(args, todo, status, running)
    except KeyboardInterrupt:
        # the runs in progress save a final checkpoint with their memory (a 100,000-frame COMPER run's
        # snapshot is ~1 GB): started again with the same arguments, the bench continues them
        stop_runs(running, 600.0)
        for p in running:
            p.logf.close()
            release_domain(p.domain)
        raise


def _run_queue(args, todo: list, status: dict, running: list) -> None:
    done = 0
    last_report = time.monotonic()
    while todo or running:
        while todo and len(running) < args.parallel:
            g, v, s = todo.pop(0)
            dom = claim_domain()
            p = launch(args, g, v, s, dom, resume=status[(g, v, s)] == "continue")
            p.domain = dom
            running.append(p)
        time.sleep(2.0)
        for p in list(running):
            if p.poll() is not None:
                running.remove(p)
                p.logf.close()
                release_domain(p.domain)
                done += 1
                print(f"[bench] done {p.rid}: exit {p.returncode}, {time.monotonic() - p.t0:.0f} s "
                      f"({done} finished, {len(todo)} queued)", flush=True)
        if time.monotonic() - last_report > args.progress_period:
            last_report = time.monotonic()
            for p in running:
                print(f"[bench]   {p.rid}: {progress_of(args, p.rid)} ({time.monotonic() - p.t0:.0f} s)", flush=True)


def _ms(values: list[float]) -> str:
    v = [x for x in values if x is not None and np.isfinite(x)]
    if not v:
        return "-"
    return f"{np.mean(v):.1f} ({np.std(v):.1f})" if len(v) > 1 else f"{v[0]:.1f}"


def _ci(values: list[float]) -> str:
    """Mean [bootstrap 95% CI of the mean over runs]."""
    from learning_bench import bootstrap_ci
    v = [x for x in values if x is not None and np.isfinite(x)]
    if not v:
        return "-"
    lo, hi = bootstrap_ci(v)
    return f"{np.mean(v):.1f} [{lo:.1f}, {hi:.1f}]" if len(v) > 1 else f"{v[0]:.1f}"


def run_record(sd: Path) -> dict:
    """The per-run figures the report needs (what runs.json keeps)."""
    s = json.loads(sd.read_text())
    from learning_bench import resumed_episodes
    eps = resumed_episodes([e for e in MetricsLog.read(sd.parent / "metrics.jsonl", "episode", missing_ok=True)
                            if e.get("source", "train") == "train"])
    return {"run_id": sd.parent.name, "game": s["env_id"].split("/")[-1].replace("-v5", ""),
            "variant": sd.parent.name.rsplit("-", 2)[0],     # the run id is <variant>-<game>-s<seed>
            "seed": s["seed"], "protocol": s["protocol"], "frames": s["frames"],
            "steps": s["steps"], "wall_time_s": s["wall_time_s"], "complete": s["complete"],
            "episode_frames": [e["frames"] for e in eps], "episode_returns": [e["ret"] for e in eps],
            "profile": s.get("profile")}


def run_protocol(record: dict, budget: int) -> dict:
    """The protocol figures of one run record: recomputed from its episodes where it keeps them, else the
    figures its summary stored."""
    if record.get("episode_frames"):
        return protocol_summary(record["episode_returns"], record["episode_frames"], budget)
    return record["protocol"]


def reference_lines(ref: dict | None, games: list[str]) -> list[str]:
    """Random play and the best constant action per game (atari_constant_actions.py's JSON, read)."""
    if ref is None:
        return []
    out = []
    for g in games:
        if g not in ref:
            continue
        rows = {a: float(np.mean(v)) for a, v in ref[g].items() if a != "random"}
        best = max(rows, key=rows.get) if rows else None
        if "random" in ref[g]:
            out.append(f"| {g} | random play (reference) | {len(ref[g]['random'])} episodes | {_ci(ref[g]['random'])} "
                       "| | | | | | | | |")
        if best is not None:
            out.append(f"| {g} | best constant action: {best} (reference) | {len(ref[g][best])} episodes | "
                       f"{rows[best]:.1f} | | | | | | | | |")
    return out


def frames_reached(record: dict) -> int:
    """The frames a run has played: its summary's, or its last episode's end where that is later (a run under
    way writes its summary when it stops or ends, its episodes as they end)."""
    return max([record["frames"], *record["episode_frames"]])


def curve_on_grid(grid: np.ndarray, frames: list, returns: list, reached: float) -> np.ndarray:
    """One run's training-episode returns on the frame grid: interpolated between episode ends, NaN before the
    first, the last episode's return held from its end up to the frames the run reached (the episode under way
    at the end of a complete run), and NaN beyond them: an unfinished run's line stops where the run stopped."""
    y = np.interp(grid, frames, returns, left=np.nan, right=returns[-1])
    y[grid > reached] = np.nan
    return y


def difference_lines(table: list[dict], baseline: str) -> tuple[list[str], list[dict]]:
    """Markdown lines and records of each variant's last-10 (3*) mean minus `baseline`'s on the same game, with
    the bootstrap 95% interval of the difference (each variant's seeds resampled on their own, as learning_bench's
    --baseline): 'above' or 'below' only where the interval excludes 0."""
    from learning_bench import difference, difference_cell
    lines = [f"Difference to {baseline} (last 10 (3*): this variant's mean minus {baseline}'s on the same game, "
             "bootstrap 95% interval with each variant's seeds resampled on their own; above / below only where it "
             "excludes 0):", "", "| game | variant | seeds (this / baseline) | difference [95% CI] |", "|---|---|---|---|"]
    ref = {e["game"]: e for e in table if e["variant"] == baseline}
    records = []
    for e in table:
        base = ref.get(e["game"])
        if base is None or e["variant"] == baseline:
            continue
        d = difference(e["last"], base["last"])
        records.append({"game": e["game"], "variant": e["variant"], "baseline": baseline, **d})
        lines.append(f"| {e['game']} | {e['variant']} | {d['n']} / {d['n_baseline']} | {difference_cell(d)} |")
    return lines, records


def random_play_lines(table: list[dict], ref: dict | None) -> list[str]:
    """Markdown lines of each variant's last-10 (3*) mean minus random play's mean on the same game (the reference
    JSON's random episodes), with the bootstrap 95% interval of the difference (seeds and episodes resampled on
    their own); sets each table entry's ``vs_random``. Nothing without a reference or without random episodes."""
    if ref is None:
        return []
    from learning_bench import difference, difference_cell
    rows = []
    for e in table:
        rnd = ref.get(e["game"], {}).get("random")
        if not rnd or not e["last"]:
            continue
        d = e["vs_random"] = difference(e["last"], rnd)
        rows.append(f"| {e['game']} | {e['variant']} | {d['n']} / {d['n_baseline']} | {difference_cell(d)} |")
    if not rows:
        return []
    return ["Difference to random play (last 10 (3*): the variant's mean minus random play's mean episode, bootstrap "
            "95% interval with the variant's seeds and random play's episodes resampled on their own; above / below "
            "only where it excludes 0):", "", "| game | variant | seeds / random episodes | difference [95% CI] |",
            "|---|---|---|---|", *rows]


def report(args) -> None:
    out = Path(args.out)
    records = {}
    for inc in args.include:
        for r in json.loads(Path(inc).read_text()):
            records[r["run_id"]] = r
    for sd in sorted((out / "runs").glob("*/summary.json")):
        records[sd.parent.name] = run_record(sd)
    (out / "runs.json").write_text(json.dumps(sorted(records.values(), key=lambda r: r["run_id"]), indent=0))
    policy = {}
    for pf in args.policy:
        policy.update({r["run"]: r for r in json.loads(Path(pf).read_text())})
    rows: dict = {}
    curves: dict = {}
    memory: dict = {}
    for rid, s in sorted(records.items()):
        if s["game"] not in args.games or s["variant"] not in args.variants:
            continue        # --games and --variants select the rows and curves, of this sweep and the includes
        if args.report_seeds is not None and s["seed"] not in args.report_seeds:
            continue
        key = (s["game"], s["variant"])
        rows.setdefault(key, []).append(s)
        curves.setdefault(s["game"], {}).setdefault(s["variant"], []).append(
            (s["episode_frames"], s["episode_returns"], frames_reached(s), s["complete"]))
        mdir = out / "runs" / rid / "metrics.jsonl"
        if mdir.exists():
            memory.setdefault(s["game"], {}).setdefault(s["variant"], []).append(
                MetricsLog.read(mdir, "memory", missing_ok=True))
    reference = json.loads(args.reference.read_text()) if args.reference else None   # read once for every game
    table = []
    lines = ["| game | variant | seeds | last 10 (3*) [95% CI] | tercile 1 | tercile 2 | tercile 3 | episodes | frames | "
             "wall (min) | steps/s | policy: on the initial greedy action everywhere; distinct greedy actions |",
             "|---|---|---|---|---|---|---|---|---|---|---|---|"]
    games = []
    for (game, alg), ss in sorted(rows.items(), key=lambda kv: (kv[0][0], VARIANTS.index(kv[0][1])
                                                                  if kv[0][1] in VARIANTS else 9)):
        if game not in games:
            if games:
                lines += reference_lines(reference, [games[-1]])
            games.append(game)
        pr = [run_protocol(s, args.frames) for s in ss]
        star = "*" if any(p["last_k"] == 3 for p in pr) else ""
        entry = {"game": game, "variant": alg, "seeds": [s["seed"] for s in ss],
                 "last": [p["last_mean"] for p in pr], "last_k": [p["last_k"] for p in pr],
                 "terciles": [[t["mean"] for t in p["terciles"]] for p in pr],
                 "episodes": [p["episodes"] for p in pr], "frames": [frames_reached(s) for s in ss],
                 "wall_s": [s["wall_time_s"] for s in ss],
                 "steps_per_s": [s["steps"] / s["wall_time_s"] if s["wall_time_s"] else None for s in ss],
                 "complete": [s["complete"] for s in ss]}
        pol = [policy[s["run_id"]] for s in ss if s["run_id"] in policy]
        if pol:
            entry["policy"] = pol
            pcell = (f"{sum(r['same_as_initial'] == 1.0 for r in pol)}/{len(pol)}; "
                     + ", ".join(str(r["distinct"]) for r in pol))
        else:
            pcell = "-"
        table.append(entry)
        terc = list(zip(*entry["terciles"])) if entry["terciles"] else [[], [], []]
        unfinished = sum(not done for done in entry["complete"])
        seeds = f"{len(ss)} ({unfinished} unfinished)" if unfinished else f"{len(ss)}"
        lines.append(f"| {game} | {alg} | {seeds} | {_ci(entry['last'])}{star} | {_ms(list(terc[0]))} | "
                     f"{_ms(list(terc[1]))} | {_ms(list(terc[2]))} | {_ms(entry['episodes'])} | "
                     f"{_ms(entry['frames'])} | {_ms([w / 60 for w in entry['wall_s']])} | "
                     f"{_ms(entry['steps_per_s'])} | {pcell} |")
    if games:
        lines += reference_lines(reference, [games[-1]])
    lines.append("")
    lines.append("last 10: mean over seeds [bootstrap 95% CI of that mean]; terciles and the rest: mean (std across "
                 "seeds); * = a run with fewer than 25 episodes reports its last 3 episodes (terciles: last 3 instead "
                 "of 5).")
    random_lines = random_play_lines(table, reference)
    if random_lines:
        lines += ["", *random_lines]
    if args.baseline:
        diff_lines, differences = difference_lines(table, args.baseline)
        lines += ["", *diff_lines]
        (out / "differences.json").write_text(json.dumps(differences, indent=1))
    (out / "table.md").write_text("\n".join(lines) + "\n")
    (out / "table.json").write_text(json.dumps(table, indent=1))
    (out / "memory.json").write_text(json.dumps(memory, indent=1))
    print("\n".join(lines))
    try:
        import matplotlib
        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError as exc:
        print(f"[bench] no figures: matplotlib not importable ({exc})")
        return
    variants = sorted({alg for by_alg in [*curves.values(), *memory.values()] for alg in by_alg})
    colour = {alg: f"C{k}" for k, alg in enumerate(variants)}   # one colour per variant, its seeds included
    for game, by_alg in curves.items():
        fig, ax = plt.subplots(figsize=(7, 4))
        grid = np.linspace(0, args.frames, 101)
        for alg, runs in by_alg.items():
            ys = [curve_on_grid(grid, fr, ret, reached) for fr, ret, reached, _ in runs if len(fr) >= 1]
            if not ys:
                continue
            y = np.array(ys)
            unfinished = sum(not done for *_, done in runs)
            label = f"{alg} ({len(ys)} seeds" + (f", {unfinished} unfinished)" if unfinished else ")")
            with warnings.catch_warnings():   # grid points before any run's first episode end are all NaN
                warnings.simplefilter("ignore", RuntimeWarning)
                ax.plot(grid, np.nanmean(y, 0), color=colour[alg], label=label)
                if len(ys) > 1:
                    ax.fill_between(grid, np.nanmin(y, 0), np.nanmax(y, 0), color=colour[alg], alpha=0.2)
            for fr, ret, *_ in runs:
                ax.scatter(fr, ret, s=6, alpha=0.5, color=colour[alg])
        ax.set_xlabel("frames (skipped ones counted)")
        ax.set_ylabel("training episode return")
        ax.set_title(f"{game}: training episodes")
        ax.legend()
        fig.tight_layout()
        fig.savefig(out / f"curve_{game}.png", dpi=110)
        plt.close(fig)
    for game, by_alg in memory.items():
        fig, axes = plt.subplots(1, 2, figsize=(11, 4))
        for alg, runs in by_alg.items():
            for k, mem in enumerate(runs):
                if not mem or "identities" not in mem[0]:
                    continue
                fr = [m["frames"] for m in mem]
                lab = f"{alg}" if k == 0 else None
                c = colour[alg]
                axes[0].plot(fr, [m["rtm_size"] for m in mem], color=c, label=f"{lab} RTM" if lab else None)
                axes[0].plot(fr, [m["identities"] for m in mem], "--", color=c,
                             label=f"{lab} identities" if lab else None)
                axes[0].plot(fr, [m["tm_sets"] for m in mem], ":", color=c, label=f"{lab} TM sets" if lab else None)
                axes[1].plot(fr, [m.get("sampled_set_size_mean", np.nan) for m in mem], color=c,
                             label=f"{lab} mean" if lab else None)
                axes[1].plot(fr, [m.get("sampled_set_size_p90", np.nan) for m in mem], "--", color=c,
                             label=f"{lab} p90" if lab else None)
        axes[0].set_xlabel("frames")
        axes[0].set_ylabel("entries")
        axes[0].set_title(f"{game}: memory sizes")
        axes[0].legend(fontsize=7)
        axes[1].set_xlabel("frames")
        axes[1].set_ylabel("transitions per similar set")
        axes[1].set_title("sizes of the sampled similar-transition sets")
        axes[1].legend(fontsize=7)
        fig.tight_layout()
        fig.savefig(out / f"memory_{game}.png", dpi=110)
        plt.close(fig)
    print(f"[bench] wrote {out / 'table.md'}, table.json, memory.json and figures in {out}")


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                 formatter_class=argparse.RawDescriptionHelpFormatter, epilog=__doc__)
    ap.add_argument("--games", nargs="+", default=GAMES,
                    help="ALE game names (ALE/<Game>-v5): the runs, and the report's rows; default: %(default)s")
    ap.add_argument("--variants", nargs="+", default=VARIANTS,
                    help=f"{', '.join(VARIANTS)} or a name defined with --variant: the runs, and the report's "
                         "rows (included runs of other variants are left out); default: the four")
    ap.add_argument("--variant", action="append", default=[], metavar="NAME=ALGORITHM:PARAM=VALUE[,PARAM=VALUE]",
                    help="a named configuration usable in --variants, e.g. dqn_n10=dqn:n_step=10 (its runs get "
                         "-p algorithm:=ALGORITHM -p PARAM:=VALUE ..., after every --ros-arg; repeatable)")
    ap.add_argument("--seeds", nargs="+", type=int, default=[0, 1, 2], help="default: %(default)s")
    ap.add_argument("--frames", type=int, default=100_000, help="frame budget per run (thesis: 100,000)")
    ap.add_argument("--max-steps", type=int, default=0, help="also stop each run after this many agent steps")
    ap.add_argument("--frame-stack", type=int, default=0, help="frames per observation for the COMPER variants "
                    "(0 = the node's default, 1); dqn always uses its default (4)")
    ap.add_argument("--parallel", type=int, default=2, help="runs at a time (default 2: a 2-core machine)")
    ap.add_argument("--out", default="benchmarks/out/atari", help="output folder (runs/, logs/, tables, figures)")
    ap.add_argument("--progress-period", type=float, default=60.0, help="seconds between progress lines")
    ap.add_argument("--ros-arg", action="append", default=[], metavar="NAME:=VALUE",
                    help="extra -p parameter for every run (repeatable)")
    ap.add_argument("--force", action="store_true", help="re-run runs whose summary.json exists")
    ap.add_argument("--report-only", action="store_true", help="only build the tables and figures")
    ap.add_argument("--include", nargs="+", default=[], metavar="RUNS_JSON",
                    help="runs.json files of earlier sweeps (kept in git): their runs join the table and curves")
    ap.add_argument("--reference", type=Path, default=None,
                    help="atari_constant_actions.py's JSON: random-play and best-constant rows per game, and each "
                         "variant's difference to random play with its interval")
    ap.add_argument("--policy", nargs="+", default=[], metavar="POLICY_JSON",
                    help="atari_policy_check.py --json output(s): the policy column")
    ap.add_argument("--report-seeds", nargs="+", type=int, default=None, metavar="SEED",
                    help="the report's rows and curves take only these seeds (default: every seed of this sweep and "
                         "the includes), e.g. to compare variants on the same seeds while one has fewer")
    ap.add_argument("--baseline", default="", metavar="VARIANT",
                    help="also a table of each variant's difference to this one per game, with its bootstrap "
                         "95%% interval (differences.json)")
    args = ap.parse_args(argv)
    args.named = parse_variants(args.variant)
    bad = [v for v in args.variants if v not in VARIANTS and v not in args.named] + \
        [n for n, (base, _) in args.named.items() if base not in VARIANTS or "-" in n]
    if bad:
        ap.error(f"unknown or unusable variant(s) {', '.join(bad)}: choose from {', '.join(VARIANTS)}, or define one "
                 "with --variant NAME=ALGORITHM:PARAM=VALUE (ALGORITHM one of those, NAME without '-')")
    if args.baseline and args.baseline not in args.variants:
        ap.error(f"--baseline {args.baseline}: not one of --variants ({', '.join(args.variants)})")
    Path(args.out).mkdir(parents=True, exist_ok=True)
    if not args.report_only:
        raise_on_sigterm()
        try:
            run_all(args)
        except ValueError as exc:
            ap.error(str(exc))
        except KeyboardInterrupt:
            print("[bench] interrupted: start it again with the same arguments to continue the unfinished runs",
                  flush=True)
            return 130
    report(args)
    return 0


if __name__ == "__main__":
    sys.exit(main())
