"""What each constant action (and uniform random play) scores on an ALE game under the benchmark's protocol.

Reference rows for the Atari table: after 100,000 frames most runs' greedy policies are one constant action
(``atari_policy_check.py``), so their returns are best read against what every constant action scores. Uses
the sim's own pipeline (comper_sim.core: full 18 actions, sticky actions 0.25, frame skip 5, no life-loss
signal, the 108,000-frame episode cap), ``--episodes`` episodes per action and ``--random-episodes`` of uniform
random play, with reset seeds 0, 1, ...

A constant action's episodes differ only through the sticky actions, so 3 score alike; random play's spread is
wide (Asterix: std ~150), and the reports test runs against its mean (atari_bench.py's "difference to random
play"), so it gets enough episodes for a tight interval of that mean.

    python benchmarks/atari_constant_actions.py --games Freeway Asterix Seaquest --json docs/results/atari/constant-actions.json
"""
from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np

from learning_bench import bootstrap_ci

from comper_sim.core.config import SimConfig
from comper_sim.core.envs import make_env


def play(env, policy, episodes: int) -> list[float]:
    returns = []
    for ep in range(episodes):
        env.reset(ep)
        total, done = 0.0, False
        while not done:
            _, r, terminated, truncated, _ = env.step(policy())
            total += float(r)
            done = terminated or truncated
        returns.append(total)
    return returns


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--games", nargs="+", default=["Freeway", "Asterix", "Seaquest"], help="ALE game names")
    ap.add_argument("--episodes", type=int, default=3, help="episodes per constant action")
    ap.add_argument("--random-episodes", type=int, default=200,
                    help="episodes of uniform random play (default %(default)s: a bootstrap 95%% interval of its mean "
                         "about +-20 on Asterix)")
    ap.add_argument("--seed", type=int, default=0, help="seed of the random policy")
    ap.add_argument("--json", type=Path, default=None, help="also write the results here")
    args = ap.parse_args()
    if args.episodes < 1 or args.random_episodes < 2:
        ap.error("--episodes must be >= 1 and --random-episodes >= 2 (an interval needs two episodes)")
    results = {}
    for game in args.games:
        t0 = time.perf_counter()
        env = make_env(SimConfig(env_id=f"ALE/{game}-v5"))
        names = env.env.unwrapped.get_action_meanings()
        rng = np.random.default_rng(args.seed)
        rows = {name: play(env, lambda a=a: a, args.episodes) for a, name in enumerate(names)}
        rows["random"] = play(env, lambda: int(rng.integers(len(names))), args.random_episodes)
        env.close()
        results[game] = rows
        means = {k: float(np.mean(v)) for k, v in rows.items() if k != "random"}
        best = max(means, key=means.get)
        print(f"## {game} ({time.perf_counter() - t0:.0f} s)\n")
        print("| action | mean return | episodes |\n|---|---|---|")
        for k, v in rows.items():
            if k == "random":
                lo, hi = bootstrap_ci(v)
                print(f"| random play | {np.mean(v):.1f} [{lo:.1f}, {hi:.1f}] (std {np.std(v):.1f}) | {len(v)} |")
                continue
            print(f"| {k}{' (best constant)' if k == best else ''} | {np.mean(v):.1f} +- {np.std(v):.1f} | "
                  f"{', '.join(f'{x:g}' for x in v)} |")
        print(flush=True)
    if args.json:
        args.json.write_text(json.dumps(results, indent=1))


if __name__ == "__main__":
    main()
