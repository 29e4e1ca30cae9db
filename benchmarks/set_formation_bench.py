"""Do similar-transition sets form on continuous tasks? Identities per transition at several delta
values, with raw keys (the thesis) and with per-dimension standardised keys, on transitions of a
gymnasium MuJoCo task (in-process: CompactMemory, no ROS).

The keys are concat(s, a, r, s'). Key modes:
* "none": the thesis's raw key;
* "running": the memory's own ``key_normalisation: running`` (running mean and standard deviation,
  frozen between reductions; a reduction every ``--reduce-every`` stored transitions, as in a run);
* "zscore": each dimension standardised with the mean and standard deviation of all the collected
  data at once (s and s' share the observation's): what "running" converges to, known in advance.
For each (task, keys, delta) it prints the identities per 1,000 transitions (1,000 = no compression),
the hit rate (transitions that joined an existing identity) and the set-size distribution (mean, p90,
max members per identity).

Transitions come from uniformly random actions (what a run's first steps look like), or with
``--policy CHECKPOINT`` from a trained actor (comcact_node or ddpg checkpoint) with Gaussian noise of
``--noise`` x the action half-range, as a run's later steps look:

    python benchmarks/set_formation_bench.py --tasks Hopper-v4 HalfCheetah-v4 --steps 20000
    python benchmarks/set_formation_bench.py --tasks Hopper-v4 --policy <run dir>/checkpoints/latest.pt
"""
from __future__ import annotations

import argparse
import json
import sys
import time

import numpy as np

from comper_memory.core import CompactMemory, MemoryConfig
from comper_msgs_py.arrays import Transitions
from comper_msgs_py.params import config_from_dict


def collect(task: str, steps: int, seed: int, policy=None, noise: float = 0.1) -> Transitions:
    import gymnasium as gym
    env = gym.make(task)
    rng = np.random.default_rng(seed)
    obs, _ = env.reset(seed=seed)
    lo, hi = env.action_space.low, env.action_space.high
    S, A, R, S2, T, U = [], [], [], [], [], []
    for _ in range(steps):
        if policy is None:
            a = rng.uniform(lo, hi).astype(np.float32)
        else:
            a = policy.actions(np.asarray(obs, np.float32)[None])[0]
            a = np.clip(a + rng.normal(0.0, noise * (hi - lo) / 2), lo, hi).astype(np.float32)
        nxt, r, term, trunc, _ = env.step(a)
        S.append(obs), A.append(a), R.append(r), S2.append(nxt), T.append(term), U.append(trunc)
        obs = nxt
        if term or trunc:
            obs, _ = env.reset()
    env.close()
    f = np.float32
    return Transitions(np.asarray(S, f), np.asarray(A, f), np.asarray(R, f), np.asarray(S2, f),
                       np.asarray(T, bool), np.asarray(U, bool), value_labels=np.zeros(len(S), f))


def standardise(t: Transitions) -> Transitions:
    obs = np.concatenate([t.states, t.next_states])
    mo, so = obs.mean(0), obs.std(0) + 1e-8
    ma, sa = t.actions.mean(0), t.actions.std(0) + 1e-8
    mr, sr = t.rewards.mean(), t.rewards.std() + 1e-8
    f = np.float32
    return Transitions(((t.states - mo) / so).astype(f), ((t.actions - ma) / sa).astype(f),
                       ((t.rewards - mr) / sr).astype(f), ((t.next_states - mo) / so).astype(f),
                       t.terminated, t.truncated, value_labels=t.value_labels)


def measure(t: Transitions, delta: float, key_normalisation: str = "none", batch: int = 1000) -> dict:
    """Store t in batches of ``batch`` transitions with a reduction after each (the reduction is when a
    running key normaliser updates its frozen map)."""
    cfg = config_from_dict(MemoryConfig, {"delta": delta, "rtm_capacity": len(t) + 1, "tm_capacity": len(t) + 1,
                                          "max_store_batch": batch, "reduce_batch": len(t),
                                          "key_normalisation": key_normalisation})
    mem = CompactMemory(cfg)
    t0 = time.perf_counter()
    for i in range(0, len(t), batch):
        mem.store(t.take(slice(i, i + batch)))
        mem.reduce()
    st = mem.stats()
    mem.reduce()                      # every set into RTM (newest label as prediction), to sample its counts
    sizes = np.asarray(mem.sample(min(st["identities"], 5000), source="rtm", rng=np.random.default_rng(0)).counts)
    return {"identities_per_1000": 1000.0 * st["identities"] / len(t), "hit_rate": st["hit_rate"],
            "key_norm_updates": st["key_norm_updates"],
            "set_size_mean": float(sizes.mean()), "set_size_p90": float(np.percentile(sizes, 90)),
            "set_size_max": int(sizes.max()), "seconds": time.perf_counter() - t0}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--tasks", nargs="+", default=["Hopper-v4", "HalfCheetah-v4"])
    ap.add_argument("--steps", type=int, default=20_000)
    ap.add_argument("--deltas", nargs="+", type=float, default=[1e-4, 1e-3, 1e-2, 1e-1, 1.0])
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--keys", nargs="+", default=["none", "running", "zscore"], choices=["none", "running", "zscore"])
    ap.add_argument("--reduce-every", type=int, default=1000, help="stored transitions between reductions")
    ap.add_argument("--policy", help="a comcact_node / ddpg checkpoint whose actor chooses the actions "
                    "(default: uniformly random actions)")
    ap.add_argument("--noise", type=float, default=0.1, help="with --policy: Gaussian action noise, "
                    "as a fraction of the action half-range")
    ap.add_argument("--json", help="also write the rows to this file")
    args = ap.parse_args(argv)
    policy = None
    if args.policy:
        from comper_agent.offline.value_checks import load_policy
        policy = load_policy(args.policy)
    rows = []
    print("| task | keys | delta | identities per 1,000 transitions | hit rate | set size mean / p90 / max |")
    print("|---|---|---|---|---|---|")
    for task in args.tasks:
        raw = collect(task, args.steps, args.seed, policy, args.noise)
        for keys in args.keys:
            t = standardise(raw) if keys == "zscore" else raw
            for d in args.deltas:
                m = measure(t, d, "running" if keys == "running" else "none", args.reduce_every)
                rows.append({"task": task, "keys": keys, "delta": d, "transitions": len(t), **m})
                print(f"| {task} | {keys} | {d:g} | {m['identities_per_1000']:.0f} | {m['hit_rate']:.3f} | "
                      f"{m['set_size_mean']:.2f} / {m['set_size_p90']:.0f} / {m['set_size_max']} |", flush=True)
    if args.json:
        with open(args.json, "w") as f:
            json.dump({"steps": args.steps, "seed": args.seed, "reduce_every": args.reduce_every,
                       "actions": "random" if policy is None else f"policy + {args.noise:g} noise",
                       "rows": rows}, f, indent=1)
    return 0


if __name__ == "__main__":
    sys.exit(main())
