"""Recording overhead and offline-evaluation time (docs/recording.md).

    python benchmarks/recording_bench.py                        # both parts, defaults below
    python benchmarks/recording_bench.py overhead --steps 6000 --step-work-ms 5 --reps 3
    python benchmarks/recording_bench.py overhead --agent-cmd "ros2 run comper_agent comcact_node --ros-args -p total_steps:=5000"
    python benchmarks/recording_bench.py evaluate --steps 50000 [--checkpoint]

overhead: an agent-like publisher loop (per step a fixed amount of CPU work calibrated to
--step-work-ms, one TransitionBatch + one EpisodeSummary per episode of Hopper-like length, the
topic contract's QoS) runs the same number of steps with and without a recorder_node process;
the throughput ratio is the recording cost (target <= 5 %). --step-work-ms 0 is the stress case
(publishing as fast as rclpy can). With --agent-cmd the command itself is the agent (run to
completion with and without the recorder; wall time compared). With --agent-cmd and
--record-param the agent records itself (``-p record:=false`` / ``-p record:=true`` appended,
alternating, each run in its own run directory) and the training loop's own steps/s (the run's
``timers`` record in metrics.jsonl, start-up excluded) is compared: the user's real set-up.

evaluate: writes a synthetic 50,000-step run's bag (as the recorder writes it) and times
``evaluate`` on it, plots included (target <= 10 s), in-process and through ``ros2 run``.
"""
from __future__ import annotations

import argparse
import json
import os
import shlex
import shutil
import signal
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "test"))   # scaffolding: synthetic runs

os.environ.setdefault("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")
os.environ.setdefault("ROS_DOMAIN_ID", str(40 + os.getpid() % 50))


def _ros2() -> str:
    exe = shutil.which("ros2")
    if not exe:
        sys.exit("no ros2 on PATH: source env.sh first")
    return exe


def start_recorder(out_dir: Path, run_id: str, topics: list[str] | None = None) -> subprocess.Popen:
    args = [_ros2(), "run", "comper_agent", "recorder_node", "--ros-args", "-p", f"output_dir:={out_dir}",
            "-p", f"run_id:={run_id}"]
    if topics:
        args += ["-p", "topics:=[" + ",".join(topics) + "]"]
    return subprocess.Popen(args, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, start_new_session=True)


def stop(proc: subprocess.Popen) -> None:
    if proc.poll() is None:
        os.killpg(proc.pid, signal.SIGINT)
        try:
            proc.wait(20)
        except subprocess.TimeoutExpired:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.wait(10)


def calibrate(work_ms: float) -> int:
    """Number of 128x128 float32 matmuls taking work_ms on this machine, alone."""
    if work_ms <= 0:
        return 0
    a = np.random.default_rng(0).standard_normal((128, 128)).astype(np.float32)
    n = 50
    while True:
        t0 = time.perf_counter()
        for _ in range(n):
            a @ a
        dt = time.perf_counter() - t0
        if dt > 0.2:
            return max(1, int(n * work_ms / 1000.0 / dt))
        n *= 2


def proc_cpu_s(pid: int) -> float:
    """user + system CPU seconds of a process (Linux /proc)."""
    try:
        f = open(f"/proc/{pid}/stat").read().rsplit(")", 1)[1].split()
        return (int(f[11]) + int(f[12])) / os.sysconf("SC_CLK_TCK")
    except (OSError, IndexError):
        return float("nan")


def publisher_loop(node, topics, steps: int, work_n: int, seed: int = 0) -> dict:
    """Agent-like loop: returns steps/s and messages published."""
    from scaffolding import synthetic_run
    t, summ = synthetic_run(steps, seed=seed, run_id="bench")
    a = np.random.default_rng(1).standard_normal((128, 128)).astype(np.float32)
    ids = t.episode_ids.astype(np.int64)
    bounds = np.flatnonzero(np.diff(ids)) + 1
    starts = np.concatenate([[0], bounds])
    ends = np.concatenate([bounds, [len(t)]])
    msgs = 0
    c0 = time.process_time()
    t0 = time.perf_counter()
    for s, lo, hi in zip(summ, starts, ends):
        for _ in range(int(hi - lo)):          # the agent's per-step work
            for _ in range(work_n):
                a @ a
        topics.transitions(t.take(slice(int(lo), int(hi))))
        topics.episode(env_id="Hopper-v4", source="train", **s)
        msgs += 2
    dt = time.perf_counter() - t0
    return {"steps_per_s": steps / dt, "seconds": dt, "cpu_s": time.process_time() - c0, "messages": msgs,
            "episodes": len(summ)}


def overhead(args) -> dict:
    if args.agent_cmd and args.record_param:
        return overhead_record_param(args)
    if args.agent_cmd:
        return overhead_agent_cmd(args)
    import rclpy
    from rclpy.node import Node

    from scaffolding import EpisodeTopics

    rclpy.init()
    node = Node("recording_bench_agent")
    topics = EpisodeTopics(node, "/comcact_node")
    work_n = calibrate(args.step_work_ms)
    print(f"per-step work: {work_n} matmuls (~{args.step_work_ms} ms alone); {args.steps} steps per run")
    results = {"with": [], "without": [], "recorded": [], "cpu_with": [], "cpu_without": [], "cpu_recorder": []}
    tmp = Path(tempfile.mkdtemp(prefix="recbench_"))
    try:
        publisher_loop(node, topics, min(args.steps, 2000), work_n)      # warm-up
        for rep in range(args.reps):
            for mode in ("without", "with"):
                rec = None
                if mode == "with":
                    rec = start_recorder(tmp, f"rep{rep}")
                    end = time.monotonic() + 30
                    while topics.transitions_pub.get_subscription_count() == 0 or \
                            topics.episodes_pub.get_subscription_count() == 0:
                        if time.monotonic() > end:
                            sys.exit("recorder did not subscribe")
                        time.sleep(0.05)
                rc0 = proc_cpu_s(rec.pid) if rec is not None else 0.0
                r = publisher_loop(node, topics, args.steps, work_n, seed=rep)
                results[mode].append(r["steps_per_s"])
                results["cpu_" + mode].append(r["cpu_s"])
                if rec is not None:
                    time.sleep(0.5)       # let the recorder drain what is in flight
                    results["cpu_recorder"].append(proc_cpu_s(rec.pid) - rc0)
                if rec is not None:
                    stop(rec)
                    from rosbags.rosbag2 import Reader
                    with Reader(tmp / f"rep{rep}" / "bag") as rd:
                        results["recorded"].append((rd.message_count, r["messages"]))
                print(f"  rep {rep} {mode:8s}: {r['steps_per_s']:9.1f} steps/s, agent CPU {r['cpu_s']:.2f} s"
                      + (f", recorder CPU {results['cpu_recorder'][-1]:.3f} s" if rec is not None else "")
                      + f" ({r['episodes']} episodes)")
    finally:
        node.destroy_node()
        rclpy.try_shutdown()
        bag_mb = sum(f.stat().st_size for f in tmp.rglob("*") if f.is_file()) / 2**20 / max(1, args.reps)
        shutil.rmtree(tmp, ignore_errors=True)
    w, wo = statistics.median(results["with"]), statistics.median(results["without"])
    cw, cwo = statistics.median(results["cpu_with"]), statistics.median(results["cpu_without"])
    crec = statistics.median(results["cpu_recorder"])
    out = {"mode": "publisher_loop", "steps": args.steps, "step_work_ms": args.step_work_ms,
           "without_steps_per_s": wo, "with_steps_per_s": w, "overhead_pct": 100.0 * (1 - w / wo),
           "agent_cpu_without_s": cwo, "agent_cpu_with_s": cw, "recorder_cpu_s": crec,
           "cpu_overhead_pct": 100.0 * (cw + crec - cwo) / cwo,
           "all": results, "bag_mb_per_run": bag_mb}
    print(f"median throughput without {wo:.1f}, with recorder {w:.1f} steps/s: overhead "
          f"{out['overhead_pct']:.2f} % (target <= 5 %); CPU: agent {cwo:.2f} s without, {cw:.2f} s with, "
          f"recorder {crec:.3f} s: CPU overhead {out['cpu_overhead_pct']:.2f} %; recorded/published {results['recorded']}")
    return out


def overhead_agent_cmd(args) -> dict:
    times = {"with": [], "without": []}
    tmp = Path(tempfile.mkdtemp(prefix="recbench_"))
    try:
        for rep in range(args.reps):
            for mode in ("without", "with"):
                rec = start_recorder(tmp, f"rep{rep}") if mode == "with" else None
                if rec:
                    time.sleep(2.0)
                t0 = time.perf_counter()
                subprocess.run(shlex.split(args.agent_cmd), check=True, stdout=subprocess.DEVNULL)
                times[mode].append(time.perf_counter() - t0)
                if rec:
                    stop(rec)
                print(f"  rep {rep} {mode:8s}: {times[mode][-1]:.2f} s")
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    w, wo = statistics.median(times["with"]), statistics.median(times["without"])
    out = {"mode": "agent_cmd", "cmd": args.agent_cmd, "without_s": wo, "with_s": w,
           "overhead_pct": 100.0 * (w / wo - 1), "all": times}
    print(f"median wall time without {wo:.2f} s, with recorder {w:.2f} s: overhead {out['overhead_pct']:.2f} %")
    return out


def overhead_record_param(args) -> dict:
    """The agent command with record:=false / record:=true alternating; steps/s from each run's timers."""
    rates = {"with": [], "without": []}
    bag_mb = []
    tmp = Path(tempfile.mkdtemp(prefix="recbench_"))
    try:
        for rep in range(args.reps):
            for mode in ("without", "with"):
                run_id = f"rep{rep}-{mode}"
                cmd = shlex.split(args.agent_cmd)
                if "--ros-args" not in cmd:
                    cmd.append("--ros-args")
                cmd += ["-p", f"record:={'true' if mode == 'with' else 'false'}", "-p", f"runs_root:={tmp}",
                        "-p", f"run_id:={run_id}"]
                subprocess.run(cmd, check=True, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
                timers = [json.loads(line) for line in (tmp / run_id / "metrics.jsonl").read_text().splitlines()
                          if '"timers"' in line]
                if not timers:
                    raise RuntimeError(f"{tmp / run_id}: no timers record in metrics.jsonl")
                rates[mode].append(float(timers[-1]["steps_per_s"]))
                if mode == "with":
                    bag_mb.append(sum(f.stat().st_size for f in (tmp / run_id / "bag").rglob("*") if f.is_file())
                                  / 2**20)
                print(f"  rep {rep} {mode:8s}: {rates[mode][-1]:.2f} steps/s", flush=True)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    w, wo = statistics.median(rates["with"]), statistics.median(rates["without"])
    spread = 100.0 * (max(rates["without"]) - min(rates["without"])) / wo
    # paired: each rep's with-run follows its without-run, so slow drifts of the machine cancel
    paired = [100.0 * (1 - a / b) for a, b in zip(rates["with"], rates["without"])]
    pm = statistics.mean(paired)
    pse = statistics.stdev(paired) / len(paired) ** 0.5 if len(paired) > 1 else float("nan")
    out = {"mode": "record_param", "cmd": args.agent_cmd, "without_steps_per_s": wo, "with_steps_per_s": w,
           "overhead_pct": 100.0 * (1 - w / wo), "spread_without_pct": spread, "all": rates,
           "paired_overhead_pct": paired, "paired_mean_pct": pm, "paired_se_pct": pse,
           "bag_mb_per_run": statistics.median(bag_mb) if bag_mb else 0.0}
    print(f"median training throughput without {wo:.2f}, with record:=true {w:.2f} steps/s: overhead "
          f"{out['overhead_pct']:.2f} % (target <= 5 %); spread of the runs without recording {spread:.1f} %; "
          f"paired per rep: {', '.join(f'{x:.1f}' for x in paired)} % -> mean {pm:.2f} +- {pse:.2f} % (standard error)")
    return out


def evaluate_time(args) -> dict:
    from comper_agent.offline.evaluate import evaluate
    from scaffolding import synthetic_run
    from scaffolding import write_run_bag
    tmp = Path(tempfile.mkdtemp(prefix="evalbench_"))
    try:
        t, summ = synthetic_run(args.eval_steps, seed=0, run_id="bench50k")
        evals = [(k, list(np.random.default_rng(k).normal(1000, 50, 10)), [1000] * 10)
                 for k in range(5000, args.eval_steps + 1, 5000)]
        t0 = time.perf_counter()
        bag = write_run_bag(tmp / "run" / "bag", t, summ, evals)
        t_write = time.perf_counter() - t0
        size = sum(f.stat().st_size for f in bag.iterdir()) / 2**20
        ckpt = None
        if args.checkpoint:
            from comper_agent.core.checkpoint import save_checkpoint
            from comper_agent.core.comcact import ComcactLearner
            from comper_agent.core.config import DDPGConfig
            lr = ComcactLearner(DDPGConfig(), t.states.shape[1], [-1] * 3, [1] * 3)
            ckpt = save_checkpoint(tmp / "ckpt.pt", {"learner": lr.state_dict()})
        t0 = time.perf_counter()
        s = evaluate([tmp / "run"], tmp / "report")
        t_eval = time.perf_counter() - t0
        t0 = time.perf_counter()
        subprocess.run([_ros2(), "run", "comper_agent", "evaluate", str(tmp / "run"), "--out", str(tmp / "r2")],
                       check=True, stdout=subprocess.DEVNULL)
        t_cli = time.perf_counter() - t0
        res = {"steps": args.eval_steps, "episodes": len(summ), "bag_mb": size, "write_s": t_write,
               "evaluate_s": t_eval, "evaluate_read_s": s["timing_s"]["read"], "evaluate_cli_s": t_cli,
               "plots": s["plots"]}
        if ckpt:
            t0 = time.perf_counter()
            s2 = evaluate([tmp / "run"], tmp / "r3", checkpoint=ckpt)
            res["evaluate_checkpoint_s"] = time.perf_counter() - t0
            res["fqe_updates"] = next(iter(s2["q_evaluation"].values()))["fqe"]["updates"]
        if args.out:
            Path(args.out).mkdir(parents=True, exist_ok=True)
            for p in s["plots"] + ["report.md"]:
                shutil.copy(tmp / "report" / p, Path(args.out) / f"evaluate_{p}")
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    print(f"evaluate on a {args.eval_steps}-step bag ({res['episodes']} episodes, {res['bag_mb']:.1f} MB): "
          f"{res['evaluate_s']:.2f} s in-process (read {res['evaluate_read_s']:.2f} s), {res['evaluate_cli_s']:.2f} s "
          f"via ros2 run (target <= 10 s)"
          + (f"; with --checkpoint (Q vs MC + FQE {res['fqe_updates']} updates): {res['evaluate_checkpoint_s']:.2f} s"
             if ckpt else ""))
    return res


def plot(results: dict, out: Path) -> None:
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    out.mkdir(parents=True, exist_ok=True)
    fig, axes = plt.subplots(1, 2, figsize=(10, 3.8))
    ov = results.get("overhead")
    if ov and ov["mode"] in ("publisher_loop", "record_param"):
        axes[0].bar(["without recorder", "with recorder"], [ov["without_steps_per_s"], ov["with_steps_per_s"]],
                    color=["tab:gray", "tab:blue"])
        axes[0].set(ylabel="agent steps/s (median)",
                    title=(f"publisher loop, {ov['step_work_ms']} ms/step" if ov["mode"] == "publisher_loop"
                           else "agent, record:=false / true") + f": overhead {ov['overhead_pct']:.2f} %")
    ev = results.get("evaluate")
    if ev:
        names = ["in-process", "ros2 run"] + (["+ checkpoint"] if "evaluate_checkpoint_s" in ev else [])
        vals = [ev["evaluate_s"], ev["evaluate_cli_s"]] + ([ev["evaluate_checkpoint_s"]] if "evaluate_checkpoint_s" in ev else [])
        axes[1].bar(names, vals, color="tab:green")
        axes[1].axhline(10, color="r", ls="--", lw=1, label="target 10 s")
        axes[1].set(ylabel="seconds", title=f"evaluate on a {ev['steps']}-step bag")
        axes[1].legend()
    fig.tight_layout()
    fig.savefig(out / "recording_bench.png", dpi=110)
    plt.close(fig)


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("part", nargs="?", default="all", choices=["all", "overhead", "evaluate"])
    p.add_argument("--steps", type=int, default=6000, help="agent steps per overhead run (default 6000)")
    p.add_argument("--step-work-ms", type=float, default=5.0,
                   help="CPU work per agent step, calibrated alone (default 5 ms = 200 steps/s, COMCACT-like; 0 = stress)")
    p.add_argument("--reps", type=int, default=2, help="repetitions of each mode (median reported)")
    p.add_argument("--agent-cmd", help="measure this agent command (run to completion) instead of the publisher loop")
    p.add_argument("--record-param", action="store_true",
                   help="with --agent-cmd: toggle the agent's own record:= parameter and compare its steps/s")
    p.add_argument("--eval-steps", type=int, default=50000, help="steps of the synthetic run for evaluate (default 50000)")
    p.add_argument("--checkpoint", action="store_true", help="also time evaluate --checkpoint (DDPG-size networks)")
    p.add_argument("--out", default="/tmp/recording_bench", help="folder for the plot and results.json")
    args = p.parse_args(argv)
    results = {}
    if args.part in ("all", "overhead"):
        results["overhead"] = overhead(args)
    if args.part in ("all", "evaluate"):
        results["evaluate"] = evaluate_time(args)
    out = Path(args.out)
    plot(results, out)
    (out / "results.json").write_text(json.dumps(results, indent=1, default=str))
    print(f"results: {out / 'results.json'}, plot: {out / 'recording_bench.png'}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
