"""How a comper_node run's greedy policy moves, checkpoint by checkpoint, on fixed states of an ALE game.

Each checkpoint's Q-network (``<run dir>/checkpoints/step_*.pt``) is evaluated on every ``--every``-th state of
one uniform-random-play episode (the sim's pipeline, frame pooling and stack as the run's config.yaml says, reset
seed ``--reset-seed``): the mean max-min Q gap, the mean max_a Q, the shares of states whose greedy action
moves up / down (action names with UP / DOWN), and the number of distinct greedy actions. With a short
``checkpoint_every`` (and ``checkpoint_replay:=false``, ``keep_checkpoints:=0``) this shows whether the network
keeps an action preference before its first reward (docs/comper.md, "Why 10-step COMPER misses Freeway's road"):

    ros2 run comper_agent comper_node --ros-args -p algorithm:=dqn -p env_id:=ALE/Freeway-v5 -p seed:=3 \\
        -p profile:=data_efficient -p n_step:=10 -p total_frames:=16384 -p checkpoint_every:=250 \\
        -p checkpoint_replay:=false -p keep_checkpoints:=0 -p run_id:=dqn-s3
    python benchmarks/checkpoint_action_gap.py runs/dqn-s3 --json gap.json
"""
from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np
import torch
import yaml

from comper_agent.offline.value_checks import load_policy
from comper_sim.core.config import SimConfig
from comper_sim.core.envs import make_env


def random_play_states(env_id: str, pooling: str, stack: int, reset_seed: int, every: int):
    """(every n-th state of one uniform-random-play episode, the game's action names)."""
    env = make_env(SimConfig(env_id=env_id, frame_stack=stack, frame_pooling=pooling))
    rng = np.random.default_rng(reset_seed)
    states, done = [env.reset(reset_seed)], False
    names = env.env.unwrapped.get_action_meanings()
    n = len(names)
    while not done:
        obs, _, terminated, truncated, _ = env.step(int(rng.integers(n)))
        states.append(obs)
        done = terminated or truncated
    env.close()
    return np.stack(states[::every]), names


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("run", type=Path, help="a comper_node run directory (config.yaml, checkpoints/step_*.pt)")
    ap.add_argument("--reset-seed", type=int, default=500, help="reset seed of the random-play episode")
    ap.add_argument("--every", type=int, default=4, help="keep every n-th state of the episode")
    ap.add_argument("--json", type=Path, default=None, help="also write the rows here")
    args = ap.parse_args()
    env = yaml.safe_load((args.run / "config.yaml").read_text())["env"]    # what the run's sim served
    env_id, spec = env["env_id"], env.get("spec", {})
    if not str(env_id).startswith("ALE/"):
        raise SystemExit(f"{env_id}: this check is for ALE games")
    stack, pooling = int(spec.get("frame_stack", 1)), spec.get("frame_pooling", "average")
    states, names = random_play_states(env_id, pooling, stack, args.reset_seed, args.every)
    states = torch.as_tensor(states)
    up, down = np.array(["UP" in a for a in names]), np.array(["DOWN" in a for a in names])
    rows = []
    checkpoints = sorted(args.run.glob("checkpoints/step_*.pt"))
    if not checkpoints:
        raise SystemExit(f"{args.run}: no checkpoints/step_*.pt")
    print(f"{env_id}: {len(states)} states of one random-play episode, {len(checkpoints)} checkpoints\n")
    print("| step | mean max-min Q | mean max Q | greedy UP | greedy DOWN | distinct greedy |\n|---|---|---|---|---|---|")
    for ck in checkpoints:
        policy = load_policy(ck)           # the Q-network, shapes from the checkpoint (format checked)
        if policy.kind != "dqn":
            raise SystemExit(f"{ck}: not a COMPER / DQN checkpoint")
        q = policy.q
        with torch.no_grad():
            v = q(states)
        greedy = v.argmax(dim=1).numpy()
        row = {"step": int(ck.stem.split("_")[1]), "q_gap": float((v.max(1).values - v.min(1).values).mean()),
               "q_mean": float(v.max(1).values.mean()), "up": float(up[greedy].mean()),
               "down": float(down[greedy].mean()), "distinct": int(len(set(greedy.tolist())))}
        rows.append(row)
        print(f"| {row['step']} | {row['q_gap']:.4f} | {row['q_mean']:.4f} | {row['up']:.2f} | {row['down']:.2f} | "
              f"{row['distinct']} |", flush=True)
    if args.json:
        args.json.write_text(json.dumps(rows, indent=1) + "\n")


if __name__ == "__main__":
    main()
