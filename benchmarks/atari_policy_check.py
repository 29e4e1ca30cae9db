"""What the greedy policy of finished COMPER / DQN runs does: the action histogram of argmax Q.

For each run folder (``<out>/runs/<run_id>`` of atari_bench.py, or any comper_node run dir) it loads
``checkpoints/latest.pt``, plays ``--states`` steps of the run's game with the sim's own ALE
pipeline (comper_sim.core, same preprocessing and frame stack as the run) under a behaviour policy
that takes the greedy action or, with probability ``--explore``, a random one (so the states are not
only the greedy policy's), and prints per run: how many distinct greedy actions, the most common
one and its share, and the mean gap between the largest and smallest Q of a state. A run whose
greedy action is the same in every state has learned an action preference, not a state-dependent
policy. The last two columns compare with the network the run started from (the learner built from
its config.yaml, same seed): whether training moved the greedy action at all.

Value scale (in the JSON rows): ``v_mean`` / ``v_std``, the mean and spread of max_a Q over the visited
states of the episodes that ended within ``--states`` steps, against ``mc_return_mean``, the discounted
(run's gamma) return, with the run's reward clip, that the check's own behaviour policy then collected
from those states, and ``v_mc_corr``, the correlation of the two over those states. The behaviour policy
is not the greedy one, so the return is a scale, not the value Q should hold; but a Q several times any
return an episode collects, or one that does not fall as the game nears its end (correlation near 0),
holds an offset rather than values.

    python benchmarks/atari_policy_check.py benchmarks/results/atari/s5/runs/*
"""
from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np
import torch
import yaml

from comper_agent.nodes.comper_node import ComperNode
from comper_agent.core.comper import ComperLearner, clip_rewards
from comper_agent.offline.value_checks import load_policy
from comper_agent.nodes.run_io import resolve_checkpoint
from comper_msgs_py.params import config_from_dict
from comper_sim.core.config import SimConfig
from comper_sim.core.envs import make_env


def initial_network(config: dict) -> torch.nn.Module:
    """The Q-network the run started from: the learner built from the run's config.yaml (same seed),
    with the node's own variant -> learner config map."""
    learner = config["learner"]
    return ComperLearner(config_from_dict(ComperNode.LEARNER_CONFIGS[learner["variant"]], learner)).q


def check(run: Path, states: int, explore: float, seed: int) -> dict:
    config = yaml.safe_load((run / "config.yaml").read_text())
    env_id = config["env"]["env_id"]
    policy = load_policy(resolve_checkpoint(run))        # the Q-network, shapes from the checkpoint
    if policy.kind != "dqn":
        raise ValueError(f"{run}: not a COMPER / DQN checkpoint")
    q, q0 = policy.q, initial_network(config)
    n = int(q.head[-1].out_features)
    pooling = config["learner"].get("frame_pooling", "average")      # runs before frame_pooling: average
    env = make_env(SimConfig(env_id=env_id, frame_stack=q.in_channels, frame_pooling=pooling))
    names = env.env.unwrapped.get_action_meanings()     # ALE's own action names, in action order
    rng = np.random.default_rng(seed)
    gamma = float(config["learner"].get("gamma", 0.99))
    reward_clip = config["learner"].get("reward_clip", "none")
    obs, greedy, gaps, greedy0 = env.reset(seed), [], [], []
    values, returns, episode = [], [], []       # episode: (max Q, clipped reward) of the one in progress
    try:
        for _ in range(states):
            with torch.no_grad():
                qv = q(torch.as_tensor(obs[None]))[0].numpy()
                greedy0.append(int(q0(torch.as_tensor(obs[None]))[0].argmax()))
            greedy.append(int(qv.argmax()))
            gaps.append(float(qv.max() - qv.min()))
            a = int(rng.integers(n)) if rng.random() < explore else greedy[-1]
            obs, r, terminated, truncated, _ = env.step(a)
            episode.append((float(qv.max()), float(clip_rewards(np.asarray([r], np.float32), reward_clip)[0])))
            if terminated or truncated:
                if terminated:           # a truncated episode's return is cut short: not counted
                    values.extend(v for v, _ in episode)
                    returns.extend(discounted_returns([rw for _, rw in episode], gamma))
                episode = []
                obs = env.reset(None)
    finally:
        env.close()
    counts, counts0 = np.bincount(greedy, minlength=n), np.bincount(greedy0, minlength=n)
    top, top0 = int(counts.argmax()), int(counts0.argmax())
    return {"run": run.name, "env_id": env_id, "distinct": int((counts > 0).sum()),
            "top_action": names[top], "top_share": float(counts[top] / len(greedy)),
            "q_gap_mean": float(np.mean(gaps)),
            "initial_top_action": names[top0], "initial_top_share": float(counts0[top0] / len(greedy0)),
            "same_as_initial": float(np.mean(np.asarray(greedy) == np.asarray(greedy0))),
            **value_scale(values, returns)}


def discounted_returns(rewards: list[float], gamma: float) -> list[float]:
    """G_t = sum_k gamma^k r_{t+k} to the episode's end, for every step t."""
    out, g = [], 0.0
    for r in reversed(rewards):
        g = r + gamma * g
        out.append(g)
    return out[::-1]


def value_scale(values: list[float], returns: list[float]) -> dict:
    """max_a Q against the discounted return collected from the same states (module text)."""
    v, g = np.asarray(values, float), np.asarray(returns, float)
    if v.size < 2:
        return {"value_states": int(v.size)}
    corr = float(np.corrcoef(v, g)[0, 1]) if v.std() > 0 and g.std() > 0 else float("nan")
    return {"value_states": int(v.size), "v_mean": float(v.mean()), "v_std": float(v.std()),
            "mc_return_mean": float(g.mean()), "mc_return_max": float(g.max()), "v_mc_corr": corr}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("runs", nargs="+", type=Path, help="run folders with config.yaml and checkpoints/latest.pt")
    ap.add_argument("--states", type=int, default=500, help="states visited per run")
    ap.add_argument("--explore", type=float, default=0.5, help="share of random actions of the behaviour policy")
    ap.add_argument("--seed", type=int, default=1234, help="sim and behaviour seed (not a training seed)")
    ap.add_argument("--json", type=Path, default=None, help="also write the rows here")
    args = ap.parse_args()
    torch.set_num_threads(1)
    rows = []
    print("| run | distinct greedy actions | most common (share) | mean max-min Q "
          "| initial network's most common (share) | states where the greedy action is the initial network's |")
    print("|---|---|---|---|---|---|")
    for run in args.runs:
        if not (run / "checkpoints" / "latest.pt").exists():
            continue
        r = check(run, args.states, args.explore, args.seed)
        rows.append(r)
        print(f"| {r['run']} | {r['distinct']} | {r['top_action']} ({r['top_share']:.0%}) | {r['q_gap_mean']:.3f} "
              f"| {r['initial_top_action']} ({r['initial_top_share']:.0%}) | {r['same_as_initial']:.0%} |", flush=True)
    if args.json:
        args.json.write_text(json.dumps(rows, indent=1))


if __name__ == "__main__":
    main()
