#!/usr/bin/env python3
"""Stable-Baselines3 DDPG with its default settings: the reference the DDPG baseline is judged by.

    make setup                                      # installs SB3 (requirements-extras.lock) next to the venv
    python benchmarks/sb3_reference.py --env-id Hopper-v4 --seed 0 --total-steps 50000 --run-dir /tmp/sb3-hopper

Not part of the suite (SB3 is not one of the product's dependencies); learning_bench.py runs it as
algorithm ``sb3_ddpg`` next to comcact and ddpg. Same protocol as comcact_node: every
``--eval-every`` steps (and at step 0) ``--eval-episodes`` deterministic episodes on a separate
environment built by the suite's own SimBridge (episode k of every evaluation reset with seed
seed + 1000 + k), written as ``eval`` records to <run-dir>/metrics.jsonl with a final ``timers``
record (steps/s over the whole run, evaluations included), so learning_bench reads all three
algorithms the same way. SB3 DDPG defaults (v2.9): MLP [400, 300] without batch norm, lr 1e-3,
batch 256, buffer 1e6, learning_starts 100, tau 0.005, gamma 0.99, train_freq 1, no action noise.
"""
from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path


def _import_sb3():
    try:
        import stable_baselines3
        return stable_baselines3
    except ImportError:
        raise SystemExit("stable-baselines3 is not importable: run `make setup` (it installs the extras of "
                         "requirements-extras.lock) and `. ./env.sh` first")


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--env-id", default="Hopper-v4")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--total-steps", type=int, default=50_000)
    ap.add_argument("--eval-every", type=int, default=5_000)
    ap.add_argument("--eval-episodes", type=int, default=10)
    ap.add_argument("--threads", type=int, default=1, help="torch intra-op threads (comcact_node uses 1)")
    ap.add_argument("--run-dir", required=True, help="writes metrics.jsonl here")
    args = ap.parse_args(argv)

    sb3 = _import_sb3()
    import gymnasium as gym
    import numpy as np
    import torch
    from stable_baselines3 import DDPG
    from stable_baselines3.common.callbacks import BaseCallback

    from comper_agent.nodes.run_io import MetricsLog
    from comper_sim.core import SimBridge, SimConfig

    torch.set_num_threads(max(1, args.threads))
    run_dir = Path(args.run_dir)
    run_dir.mkdir(parents=True, exist_ok=True)
    metrics = MetricsLog(run_dir / "metrics.jsonl")
    metrics.write("config", algorithm="sb3_ddpg", env_id=args.env_id, seed=args.seed, sb3_version=sb3.__version__,
                  total_steps=args.total_steps, eval_every=args.eval_every, eval_episodes=args.eval_episodes)
    eval_seed = args.seed + 1000
    bridge = SimBridge(SimConfig(env_id=args.env_id, seed=eval_seed, episode_end="standard",
                                 action_out_of_range="clip"))
    t_start = time.monotonic()
    eval_time = [0.0]

    def evaluate(model, step: int) -> None:
        t0 = time.monotonic()
        rets, lens = [], []
        for k in range(args.eval_episodes):
            ret, n, _ = bridge.play_episode(
                lambda obs: np.asarray(model.predict(np.asarray(obs, np.float32), deterministic=True)[0],
                                       np.float32), eval_seed + k)
            rets.append(ret)
            lens.append(n)
        eval_time[0] += time.monotonic() - t0
        metrics.write("eval", step=step, mean_return=float(np.mean(rets)), std_return=float(np.std(rets)),
                      returns=rets, lengths=lens, wall_time_s=time.monotonic() - t_start)
        print(f"[sb3_ddpg {args.env_id} s{args.seed}] step {step}: eval {np.mean(rets):.1f} +- {np.std(rets):.1f} "
              f"({step / max(1e-9, time.monotonic() - t_start):.1f} steps/s so far)", flush=True)

    class EvalEvery(BaseCallback):
        def _on_step(self) -> bool:
            if args.eval_every > 0 and self.num_timesteps % args.eval_every == 0:
                evaluate(self.model, self.num_timesteps)
            return True

    env = gym.make(args.env_id)
    model = DDPG("MlpPolicy", env, seed=args.seed, verbose=0, device="cpu")
    if args.eval_every > 0:
        evaluate(model, 0)
    model.learn(args.total_steps, callback=EvalEvery())
    elapsed = time.monotonic() - t_start
    metrics.write("timers", elapsed_s=elapsed, steps=args.total_steps, steps_per_s=args.total_steps / elapsed,
                  phases={"eval": {"seconds": eval_time[0]}, "sb3_learn": {"seconds": elapsed - eval_time[0]}},
                  ros_round_trip_ms=0.0, service_calls=0)
    metrics.close()
    bridge.close()
    print(f"[sb3_ddpg {args.env_id} s{args.seed}] done: {args.total_steps} steps in {elapsed:.0f} s "
          f"({args.total_steps / elapsed:.1f} steps/s)", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
