"""Do similar-transition sets form on continuous tasks? Identities per transition at several delta
values, with raw keys (the thesis) and with per-dimension standardised keys, on transitions of a
gymnasium MuJoCo task (in-process: CompactMemory, no ROS).

The keys are concat(s, a, r, s'). "zscore" standardises each dimension with the mean and standard
deviation of the collected data (s and s' share the observation's), which is what a key normaliser
frozen per reduction would converge to; "none" is the thesis's raw key. For each (task, keys, delta)
it prints the identities per 1,000 transitions (1,000 = no compression), the hit rate (transitions that
joined an existing identity) and the set-size distribution (mean, p90, max members per identity).

Transitions come from uniformly random actions (what a run's first steps look like), so they spread
more than a converged policy's: a lower bound on the compression a learning run would see.

    python benchmarks/set_formation_bench.py --tasks Hopper-v4 HalfCheetah-v4 --steps 20000
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


def collect(task: str, steps: int, seed: int) -> Transitions:
    import gymnasium as gym
    env = gym.make(task)
    rng = np.random.default_rng(seed)
    obs, _ = env.reset(seed=seed)
    S, A, R, S2, T, U = [], [], [], [], [], []
    for _ in range(steps):
        a = rng.uniform(env.action_space.low, env.action_space.high).astype(np.float32)
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


def measure(t: Transitions, delta: float, batch: int = 1000) -> dict:
    cfg = config_from_dict(MemoryConfig, {"delta": delta, "rtm_capacity": len(t) + 1, "tm_capacity": len(t) + 1,
                                          "max_store_batch": batch, "reduce_batch": len(t)})
    mem = CompactMemory(cfg)
    t0 = time.perf_counter()
    for i in range(0, len(t), batch):
        mem.store(t.take(slice(i, i + batch)))
    st = mem.stats()
    mem.reduce()                      # every set into RTM (newest label as prediction), to sample its counts
    sizes = np.asarray(mem.sample(min(st["identities"], 5000), source="rtm", rng=np.random.default_rng(0)).counts)
    return {"identities_per_1000": 1000.0 * st["identities"] / len(t), "hit_rate": st["hit_rate"],
            "set_size_mean": float(sizes.mean()), "set_size_p90": float(np.percentile(sizes, 90)),
            "set_size_max": int(sizes.max()), "seconds": time.perf_counter() - t0}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--tasks", nargs="+", default=["Hopper-v4", "HalfCheetah-v4"])
    ap.add_argument("--steps", type=int, default=20_000)
    ap.add_argument("--deltas", nargs="+", type=float, default=[1e-4, 1e-3, 1e-2, 1e-1, 1.0])
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--json", help="also write the rows to this file")
    args = ap.parse_args(argv)
    rows = []
    print("| task | keys | delta | identities per 1,000 transitions | hit rate | set size mean / p90 / max |")
    print("|---|---|---|---|---|---|")
    for task in args.tasks:
        raw = collect(task, args.steps, args.seed)
        for keys, t in (("none", raw), ("zscore", standardise(raw))):
            for d in args.deltas:
                m = measure(t, d)
                rows.append({"task": task, "keys": keys, "delta": d, "transitions": len(t), **m})
                print(f"| {task} | {keys} | {d:g} | {m['identities_per_1000']:.0f} | {m['hit_rate']:.3f} | "
                      f"{m['set_size_mean']:.2f} / {m['set_size_p90']:.0f} / {m['set_size_max']} |", flush=True)
    if args.json:
        with open(args.json, "w") as f:
            json.dump({"steps": args.steps, "seed": args.seed, "rows": rows}, f, indent=1)
    return 0


if __name__ == "__main__":
    sys.exit(main())
