#!/usr/bin/env python3
"""A third-party learner on the compact memory: Stable-Baselines3 TD3 whose replay buffer is a
memory node in another process (comper_memory.sb3.CompactReplayBuffer). Nothing of comper_agent
is used: this is what any SB3 user writes.

    ros2 run comper_memory memory_node &                      # the memory service (any host on the ROS graph)
    python examples/sb3_td3_through_memory.py --env-id Hopper-v4 --total-steps 50000

    python examples/sb3_td3_through_memory.py --spawn-memory --total-steps 300   # starts its own memory node

At the end it prints the memory's statistics (identities, similarity hits) and a deterministic
evaluation of the trained policy, and writes them as JSON with --out. On a fresh memory node the same
--seed gives the same evaluation: SB3 seeds the buffer's sampling stream with the model's seed.
"""
from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import sys
import time


def parse_args(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--env-id", default="Hopper-v4")
    ap.add_argument("--total-steps", type=int, default=50_000)
    ap.add_argument("--learning-starts", type=int, default=1_000)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--memory-node", default="memory_node", help="name of the running memory node")
    ap.add_argument("--spawn-memory", action="store_true",
                    help="start a memory node as a child process (`ros2 run comper_memory memory_node`) and stop it "
                         "at the end")
    ap.add_argument("--eval-episodes", type=int, default=5)
    ap.add_argument("--out", default="", help="write the summary as JSON here")
    return ap.parse_args(argv)


def main(argv=None) -> int:
    args = parse_args(argv)
    import gymnasium as gym
    import numpy as np
    import torch
    from stable_baselines3 import TD3
    from stable_baselines3.common.noise import NormalActionNoise

    from comper_memory.sb3 import CompactReplayBuffer

    torch.set_num_threads(1)
    child = None
    if args.spawn_memory:
        ros2 = shutil.which("ros2") or "ros2"
        child = subprocess.Popen([ros2, "run", "comper_memory", "memory_node", "--ros-args",
                                  "-r", f"__node:={args.memory_node}", "-p", "stats_period_s:=0.0"],
                                 start_new_session=True)
    try:
        env = gym.make(args.env_id)
        n_act = env.action_space.shape[-1]
        model = TD3("MlpPolicy", env, seed=args.seed, learning_starts=args.learning_starts, verbose=0,
                    action_noise=NormalActionNoise(np.zeros(n_act), 0.1 * np.ones(n_act)),
                    replay_buffer_class=CompactReplayBuffer,
                    replay_buffer_kwargs={"memory_node": args.memory_node, "timeout": 60.0})
        t0 = time.monotonic()
        model.learn(args.total_steps)
        elapsed = time.monotonic() - t0
        stats = model.replay_buffer.buffer.stats()     # after the last collected transitions are stored
        model.replay_buffer.close()
        returns = []
        eval_env = gym.make(args.env_id)
        for k in range(args.eval_episodes):
            obs, _ = eval_env.reset(seed=10_000 + k)
            done, ret = False, 0.0
            while not done:
                action, _ = model.predict(obs, deterministic=True)
                obs, r, term, trunc, _ = eval_env.step(action)
                ret += float(r)
                done = term or trunc
            returns.append(ret)
        summary = {"env_id": args.env_id, "total_steps": args.total_steps, "seed": args.seed,
                   "steps_per_s": args.total_steps / elapsed, "eval_returns": returns,
                   "eval_mean_return": float(np.mean(returns)),
                   "memory": {k: stats[k] for k in ("identities", "transitions_stored", "similarity_hits",
                                                    "rtm_size", "reductions", "rate_samples")}}
        print(json.dumps(summary, indent=1))
        if args.out:
            with open(args.out, "w") as f:
                json.dump(summary, f, indent=1)
        return 0
    finally:
        if child is not None:
            os.killpg(child.pid, 2)
            try:
                child.wait(30)
            except subprocess.TimeoutExpired:
                os.killpg(child.pid, 9)


if __name__ == "__main__":
    sys.exit(main())
