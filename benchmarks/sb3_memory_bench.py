#!/usr/bin/env python3
"""Stable-Baselines3 TD3 through the memory service against TD3 on SB3's own replay buffer, side by side.

    . ./env.sh
    python benchmarks/sb3_memory_bench.py --env-id Pendulum-v1 --steps 3000 --rounds 2

Each round trains two fresh TD3 models for ``--steps`` environment steps with the same seed and settings:
one on SB3's in-process ``ReplayBuffer``, one on ``comper_memory.sb3.CompactReplayBuffer`` against a memory
node started for that run (``ros2 run comper_memory memory_node``, its own process; its start is not timed).
It prints both rates (environment steps per second over the whole ``learn`` call) per round, their medians,
the ratio of the medians (memory / own buffer) and each round's ratio; then the CPU time per step of the
learner process (all its threads) in both variants and of the memory node, which say what the rates would
be with a core free for each process (the wall-clock rates follow the machine's other load). The two
variants alternate within a round so drift of the machine's load hits both. ``--store-every`` and
``--prefetch`` are CompactReplayBuffer's settings (0 and -1: its defaults).
"""
from __future__ import annotations

import argparse
import json
import os
import shutil
import statistics
import subprocess
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_args import raise_on_sigterm, stop_node  # noqa: E402


def parse_args(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--env-id", default="Pendulum-v1")
    ap.add_argument("--steps", type=int, default=3000, help="environment steps per model")
    ap.add_argument("--learning-starts", type=int, default=100)
    ap.add_argument("--rounds", type=int, default=2, help="pairs of runs (own buffer, memory)")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--store-every", type=int, default=0, help="CompactReplayBuffer store_every (0: its default)")
    ap.add_argument("--prefetch", type=int, default=-1, help="CompactReplayBuffer prefetch (-1: its default)")
    ap.add_argument("--threads", type=int, default=1, help="torch intra-op threads")
    ap.add_argument("--json", default="", help="write the rates as JSON here")
    return ap.parse_args(argv)


def start_memory(name: str) -> subprocess.Popen:
    ros2 = shutil.which("ros2") or "ros2"
    return subprocess.Popen([ros2, "run", "comper_memory", "memory_node", "--ros-args", "-r", f"__node:={name}",
                             "-p", "stats_period_s:=0.0"], start_new_session=True,
                            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)


def group_cpu_s(pgid: int) -> float:
    """CPU seconds (user + system) used so far by the live processes of a process group (the memory node)."""
    total, tick = 0.0, os.sysconf("SC_CLK_TCK")
    for entry in os.listdir("/proc"):
        if not entry.isdigit():
            continue
        try:
            with open(f"/proc/{entry}/stat") as f:
                fields = f.read().rsplit(")", 1)[1].split()
        except OSError:
            continue
        if int(fields[2]) == pgid:           # fields after the name: state ppid pgrp ... utime(12) stime(13)
            total += (int(fields[11]) + int(fields[12])) / tick
    return total


def train(args, memory_node: str | None, node_pgid: int = 0) -> tuple[float, dict]:
    """Steps per second of one TD3 run (memory_node None: SB3's own buffer), its CPU use per step and what the
    memory saw."""
    import gymnasium as gym
    import numpy as np
    from stable_baselines3 import TD3
    from stable_baselines3.common.noise import NormalActionNoise

    env = gym.make(args.env_id)
    n_act = env.action_space.shape[-1]
    kwargs = {}
    if memory_node is not None:
        from comper_memory.sb3 import CompactReplayBuffer
        rb_kwargs = {"memory_node": memory_node, "timeout": 60.0}
        if args.store_every:
            rb_kwargs["store_every"] = args.store_every
        if args.prefetch >= 0:
            rb_kwargs["prefetch"] = args.prefetch
        kwargs = {"replay_buffer_class": CompactReplayBuffer, "replay_buffer_kwargs": rb_kwargs}
    model = TD3("MlpPolicy", env, seed=args.seed, learning_starts=args.learning_starts, verbose=0,
                action_noise=NormalActionNoise(np.zeros(n_act), 0.1 * np.ones(n_act)), **kwargs)
    info = {}
    if memory_node is not None:   # the first call waits for discovery: not part of the rate
        model.replay_buffer.buffer.memory.stats()
    node0 = group_cpu_s(node_pgid) if node_pgid else 0.0
    t0, c0 = time.perf_counter(), time.process_time()
    model.learn(args.steps)
    rate = args.steps / (time.perf_counter() - t0)
    info["learner_cpu_ms"] = (time.process_time() - c0) / args.steps * 1e3
    if memory_node is not None:
        info["node_cpu_ms"] = (group_cpu_s(node_pgid) - node0) / args.steps * 1e3
        s = model.replay_buffer.buffer.stats()
        info.update({k: s[k] for k in ("identities", "transitions_stored", "rtm_size", "reductions")})
        model.replay_buffer.close()
    return rate, info


def main(argv=None) -> int:
    args = parse_args(argv)
    raise_on_sigterm()
    import torch
    torch.set_num_threads(max(1, args.threads))
    own, mem, own_cpu, mem_cpu, node_cpu = [], [], [], [], []
    for r in range(args.rounds):
        order = ("own", "memory") if r % 2 == 0 else ("memory", "own")
        for variant in order:
            if variant == "own":
                rate, info = train(args, None)
                own.append(rate)
                own_cpu.append(info["learner_cpu_ms"])
                print(f"[bench] round {r}: own buffer  {rate:7.1f} steps/s  {json.dumps(info)}", flush=True)
                continue
            name = f"sb3_bench_mem_{os.getpid()}_{r}"
            proc = start_memory(name)
            try:
                rate, info = train(args, name, proc.pid)
            finally:
                stop_node(proc)
            mem.append(rate)
            mem_cpu.append(info["learner_cpu_ms"])
            node_cpu.append(info["node_cpu_ms"])
            print(f"[bench] round {r}: memory      {rate:7.1f} steps/s  {json.dumps(info)}", flush=True)
    o, m = statistics.median(own), statistics.median(mem)
    paired = [b / a for a, b in zip(own, mem)]
    oc, mc, nc = statistics.median(own_cpu), statistics.median(mem_cpu), statistics.median(node_cpu)
    print(f"{args.env_id}, {args.steps} steps, learning_starts {args.learning_starts}, {args.rounds} rounds: "
          f"own buffer {o:.1f} steps/s, memory {m:.1f} steps/s (medians), ratio {m / o:.3f}; per round "
          + ", ".join(f"{x:.3f}" for x in paired) + f" (median {statistics.median(paired):.3f})")
    print(f"CPU per step (medians): learner on its own buffer {oc:.2f} ms, learner on the memory {mc:.2f} ms "
          f"(ratio {oc / mc:.3f}), memory node {nc:.2f} ms (learner + node: ratio {oc / (mc + nc):.3f})")
    if args.json:
        Path(args.json).write_text(json.dumps({"env_id": args.env_id, "steps": args.steps, "own": own,
                                               "memory": mem, "ratio": m / o, "paired": paired}, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
