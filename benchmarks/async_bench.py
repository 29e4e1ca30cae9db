#!/usr/bin/env python3
"""Lock step against async mode, side by side in one run (docs/comcact.md, "Async mode: speed").

    python benchmarks/async_bench.py                                  # Hopper-v4, 3,000 steps per row
    python benchmarks/async_bench.py --steps 50000 --tag full        # the target's run length
    python benchmarks/async_bench.py --skip-rows --actors 1 2 4      # only the actor scaling

1. **Throughput rows** (one after the other, each alone on the machine, embedded bring-up, no evaluation):
   comcact_node COMCACT and DDPG in lock step and in async mode (1 actor process), Stable-Baselines3 DDPG
   (benchmarks/sb3_reference.py, its defaults) and a minimal in-process loop (ComcactLearner + ReplayBuffer +
   gymnasium, no ROS, batch 64) as references. Each row: environment steps/s over the whole run (start-up
   included) and the achieved update-to-data ratio (updates / environment steps).
2. **Actor scaling**: a memory node and N actor_node processes with random actions (no learner), N in
   --actors; environment steps/s into the memory, measured from its stats between 10 % and 90 % of the
   transitions, and the ratio to one actor.

Learning curves of async against lock step use learning_bench.py with a variant:
    python benchmarks/learning_bench.py --tasks Hopper-v4 InvertedPendulum-v4 --algorithms comcact comcact_async \\
        --variant comcact_async=comcact:mode=async,num_actors=1 --seeds 3

Writes <out>/<tag>/{results.md, results.json, logs/, runs/}.
"""
from __future__ import annotations

import argparse
import json
import os
import random
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def parse_args(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--env-id", default="Hopper-v4")
    ap.add_argument("--steps", type=int, default=3000, help="environment steps per throughput row")
    ap.add_argument("--actors", type=int, nargs="+", default=[1, 2, 4], help="actor counts of the scaling part")
    ap.add_argument("--scaling-steps", type=int, default=4000, help="steps per actor in the scaling part")
    ap.add_argument("--rows", nargs="+", default=["comcact", "comcact_async", "ddpg", "ddpg_async", "sb3_ddpg",
                                                  "minimal"])
    ap.add_argument("--skip-rows", action="store_true", help="only the actor scaling")
    ap.add_argument("--skip-scaling", action="store_true", help="only the throughput rows")
    ap.add_argument("--out", default=str(ROOT / "benchmarks" / "results" / "async"))
    ap.add_argument("--tag", default=time.strftime("%Y%m%d-%H%M%S"))
    return ap.parse_args(argv)


def _env(domain: int) -> dict:
    return {**os.environ, "ROS_DOMAIN_ID": str(domain), "ROS_AUTOMATIC_DISCOVERY_RANGE": "LOCALHOST",
            "OMP_NUM_THREADS": "1"}


def _run(cmd, log: Path, domain: int, timeout: float) -> tuple[int, float]:
    t0 = time.monotonic()
    with open(log, "wb") as f:
        p = subprocess.Popen(cmd, stdout=f, stderr=subprocess.STDOUT, env=_env(domain), start_new_session=True)
        try:
            rc = p.wait(timeout)
        except subprocess.TimeoutExpired:
            os.killpg(p.pid, signal.SIGINT)
            rc = p.wait(60)
    return rc, time.monotonic() - t0


def node_row(args, base: Path, name: str, domain: int) -> dict:
    import torch
    from comper_agent.nodes.run_io import MetricsLog
    alg, _, mode = name.partition("_")
    rid = name
    cmd = [shutil.which("ros2") or "ros2", "run", "comper_agent", "comcact_node", "--ros-args",
           "-p", f"algorithm:={alg}", "-p", f"env_id:={args.env_id}", "-p", f"total_steps:={args.steps}",
           "-p", "eval_every:=0", "-p", "tensorboard:=false", "-p", "transport_probe_calls:=0",
           "-p", f"runs_root:={base / 'runs'}", "-p", f"run_id:={rid}", "-p", "progress_period_s:=30.0",
           "-p", f"mode:={'async' if mode == 'async' else 'lockstep'}", "-p", "num_actors:=1"]
    rc, wall = _run(cmd, base / "logs" / f"{rid}.log", domain, 6 * 3600)
    run = base / "runs" / rid
    timers = MetricsLog.read(run / "metrics.jsonl", "timers", missing_ok=True)
    state = torch.load(run / "checkpoints" / "latest.pt", weights_only=True)["state"] if rc == 0 else None
    steps = state["counters"]["step"] if state else 0
    updates = state["learner"]["updates"] if state else 0
    return {"row": name, "rc": rc, "steps": steps, "updates": updates, "wall_s": wall,
            "steps_per_s": timers[-1]["steps_per_s"] if timers else float("nan"),
            "update_to_data": updates / steps if steps else float("nan")}


def sb3_row(args, base: Path, domain: int) -> dict:
    from comper_agent.nodes.run_io import MetricsLog
    run = base / "runs" / "sb3_ddpg"
    cmd = [sys.executable, str(ROOT / "benchmarks" / "sb3_reference.py"), "--env-id", args.env_id,
           "--total-steps", str(args.steps), "--eval-every", "0", "--run-dir", str(run)]
    rc, wall = _run(cmd, base / "logs" / "sb3_ddpg.log", domain, 6 * 3600)
    t = MetricsLog.read(run / "metrics.jsonl", "timers", missing_ok=True)
    # SB3 DDPG defaults: learning_starts 100, train_freq 1, gradient_steps 1
    return {"row": "sb3_ddpg", "rc": rc, "steps": args.steps, "updates": max(0, args.steps - 100), "wall_s": wall,
            "steps_per_s": t[-1]["steps_per_s"] if t else float("nan"),
            "update_to_data": max(0, args.steps - 100) / args.steps}


def minimal_row(args) -> dict:
    """A DDPG loop with no ROS and no memory service: the learner core and a replay buffer in process."""
    import gymnasium as gym
    import numpy as np
    from comper_agent.core.comcact import ComcactLearner
    from comper_agent.core.config import DDPGConfig
    from comper_agent.core.networks import configure_torch
    from comper_agent.core.replay import ReplayBuffer
    from comper_msgs_py.arrays import Transitions
    configure_torch(1)
    t0 = time.monotonic()
    env = gym.make(args.env_id)
    obs, _ = env.reset(seed=0)
    low, high = env.action_space.low, env.action_space.high
    lrn = ComcactLearner(DDPGConfig(num_threads=1), int(np.prod(env.observation_space.shape)), low, high)
    buf = ReplayBuffer(100_000, env.observation_space.shape, low.shape, seed=0)
    for step in range(args.steps):
        a = lrn.act(obs.astype(np.float32), explore=True)
        nxt, r, term, trunc, _ = env.step(a)
        buf.add(Transitions(obs[None].astype(np.float32), a[None], np.array([r], np.float32),
                            nxt[None].astype(np.float32), np.array([term]), np.array([trunc])))
        if step + 1 >= 64:
            lrn.update(buf.sample(64))
            lrn.soft_update()
        obs = env.reset()[0] if term or trunc else nxt
        if term or trunc:
            lrn.reset_noise()
    wall = time.monotonic() - t0
    return {"row": "minimal", "rc": 0, "steps": args.steps, "updates": lrn.updates, "wall_s": wall,
            "steps_per_s": args.steps / wall, "update_to_data": lrn.updates / args.steps}


def scaling(args, base: Path, n: int, domain: int) -> dict:
    """N random actors into one memory node: steps/s into the memory between 10 % and 90 % of the total."""
    from comper_memory.client import MemoryClient
    ros2 = shutil.which("ros2") or "ros2"
    mem = f"mem_scale_{os.getpid()}"
    env = _env(domain)
    logs = base / "logs"
    procs = [subprocess.Popen([ros2, "run", "comper_memory", "memory_node", "--ros-args", "-r", f"__node:={mem}",
                               "-p", "stats_period_s:=0.0"], stdout=open(logs / f"scale{n}_memory.log", "wb"),
                              stderr=subprocess.STDOUT, env=env, start_new_session=True)]
    os.environ["ROS_DOMAIN_ID"] = str(domain)
    client = MemoryClient.standalone(mem, timeout=30.0)
    try:
        if not client.wait_for_service(60.0):
            raise RuntimeError("memory node did not come up")
        for i in range(n):
            procs.append(subprocess.Popen(
                [ros2, "run", "comper_agent", "actor_node", "--ros-args", "-r", f"__node:=scale_actor_{i}",
                 "-p", f"env_id:={args.env_id}", "-p", f"seed:={i}", "-p", f"actor_id:={i}", "-p", f"memory_node:={mem}",
                 "-p", "policy:=random", "-p", f"total_steps:={args.scaling_steps}"],
                stdout=open(logs / f"scale{n}_actor{i}.log", "wb"), stderr=subprocess.STDOUT, env=env,
                start_new_session=True))
        total = n * args.scaling_steps
        samples = []
        deadline = time.monotonic() + 3600
        while time.monotonic() < deadline:
            stored = client.stats()["transitions_stored"]
            samples.append((time.monotonic(), stored))
            if stored >= total or all(p.poll() is not None for p in procs[1:]):
                break
            time.sleep(0.25)
        lo = next((t, s) for t, s in samples if s >= 0.1 * total)
        hi = next(((t, s) for t, s in samples if s >= 0.9 * total), samples[-1])
        rate = (hi[1] - lo[1]) / max(hi[0] - lo[0], 1e-9)
        return {"actors": n, "stored": samples[-1][1], "steps_per_s": rate}
    finally:
        client.close()
        for p in procs:
            if p.poll() is None:
                os.killpg(p.pid, signal.SIGINT)
        for p in procs:
            try:
                p.wait(30)
            except subprocess.TimeoutExpired:
                os.killpg(p.pid, signal.SIGKILL)


def main(argv=None) -> int:
    args = parse_args(argv)
    base = Path(args.out) / args.tag
    (base / "logs").mkdir(parents=True, exist_ok=True)
    domain = random.SystemRandom().randint(101, 231)
    out = {"env_id": args.env_id, "steps": args.steps, "date": time.strftime("%Y-%m-%d"), "rows": [], "scaling": []}
    if not args.skip_rows:
        for name in args.rows:
            print(f"[async_bench] row {name} ...", flush=True)
            row = (sb3_row(args, base, domain) if name == "sb3_ddpg" else minimal_row(args) if name == "minimal"
                   else node_row(args, base, name, domain))
            print(f"[async_bench]   {row}", flush=True)
            out["rows"].append(row)
    if not args.skip_scaling:
        for n in args.actors:
            print(f"[async_bench] {n} random actors ...", flush=True)
            r = scaling(args, base, n, domain)
            print(f"[async_bench]   {r}", flush=True)
            out["scaling"].append(r)
    md = [f"# Lock step vs async, {args.env_id}, {args.steps} steps per row ({out['date']})", "",
          "| row | steps/s | update-to-data | ratio to the same algorithm in lock step | exit |", "|---|---|---|---|---|"]
    by = {r["row"]: r for r in out["rows"]}
    for r in out["rows"]:
        ref = by.get(r["row"].replace("_async", "")) if r["row"].endswith("_async") else None
        ratio = f"{r['steps_per_s'] / ref['steps_per_s']:.2f}x" if ref else ""
        md.append(f"| {r['row']} | {r['steps_per_s']:.1f} | {r['update_to_data']:.3f} | {ratio} | {r['rc']} |")
    if out["scaling"]:
        one = out["scaling"][0]["steps_per_s"]
        md += ["", "| random actors | steps/s into the memory | ratio to the first row |", "|---|---|---|"]
        md += [f"| {s['actors']} | {s['steps_per_s']:.1f} | {s['steps_per_s'] / one:.2f}x |" for s in out["scaling"]]
    (base / "results.md").write_text("\n".join(md) + "\n")
    (base / "results.json").write_text(json.dumps(out, indent=1))
    print("\n".join(md))
    return 0


if __name__ == "__main__":
    sys.exit(main())
