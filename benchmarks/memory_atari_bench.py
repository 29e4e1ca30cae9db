#!/usr/bin/env python3
"""Store cost of the compact memory on real Atari transitions, as comper_node stores them.

Random keys (memory_core_bench.py) spread evenly over every direction; real frames do not:
most of a Freeway frame is the same road, and frames differ by a few sprites. This benchmark
plays --transitions ALE steps with the suite's own ALE pipeline (comper_sim.core, method.md
section 5 protocol: 84x84 luminance, frame skip 5, sticky actions 0.25; a mostly-UP policy with
random actions mixed in), then replays comper_node's store pattern into one CompactMemory per
--dims value, in the same run: every 4 steps one store call of the 4 new transitions plus 32
re-stores of earlier ones (the updated batch). For each 1,000 steps it prints the mean store
time and the exact re-checks per stored transition (``candidates_checked``).

``--dims`` sets ``index_projection_dim``: the grid partitions on min(3, dims) PCA directions and
filters candidates on all of them; 3 is the filter of session 3 (cells and filter on the same 3
coordinates), the default 8 the current one. Decisions are identical (exact float64 re-check);
the benchmark also checks that the identity ids agree between the settings.

    python benchmarks/memory_atari_bench.py                          # Freeway, 6,000 steps, dims 3 and 8
    python benchmarks/memory_atari_bench.py --game ALE/Seaquest-v5 --transitions 10000 --dims 3 8 16
"""
from __future__ import annotations

import argparse
import time

import numpy as np

import comper_memory.core.index as index_mod
from comper_memory.core import CompactMemory, MemoryConfig
from comper_msgs_py.arrays import Transitions
from comper_sim.core.config import SimConfig
from comper_sim.core.envs import make_env

from bench_args import add_blas_threads, apply_blas_threads


def play(game: str, n: int, seed: int) -> Transitions:
    env = make_env(SimConfig(env_id=game))
    rng = np.random.default_rng(seed)
    obs = env.reset(seed)
    S = np.zeros((n, *obs.shape), np.uint8)
    S2 = np.zeros_like(S)
    A = np.zeros(n, np.int64)
    R = np.zeros(n, np.float32)
    T = np.zeros(n, bool)
    for i in range(n):
        a = 2 if rng.random() < 0.7 else int(rng.integers(env.num_actions))  # 2 = UP
        nxt, r, term, trunc, _ = env.step(a)
        S[i], A[i], R[i], S2[i], T[i] = obs, a, r, nxt, term
        obs = env.reset(None) if (term or trunc) else nxt
    env.close()
    return Transitions(S, A, R, S2, T, np.zeros(n, bool), value_labels=np.zeros(n, np.float32),
                       episode_ids=np.zeros(n, np.uint64), steps=np.arange(n, dtype=np.uint64))


def run(t: Transitions, dims: int, every: int, seed: int) -> tuple[list[tuple], np.ndarray]:
    checked = [0]
    orig = index_mod.GridIndex.resolve

    def counting(self, *args, **kwargs):
        res = orig(self, *args, **kwargs)
        checked[0] += res.candidates_checked
        return res

    index_mod.GridIndex.resolve = counting
    try:
        mem = CompactMemory(MemoryConfig(index_projection_dim=dims))
        rng = np.random.default_rng(seed)
        rows, ids = [], []
        spent, calls, stored = 0.0, 0, 0
        n = len(t)
        for i in range(0, n, 4):
            new = np.arange(i, min(i + 4, n))
            old = rng.integers(0, i, 32) if i >= 32 else np.zeros(0, np.int64)
            batch = t.take(np.concatenate([new, old]))
            t0 = time.perf_counter()
            res = mem.store(batch)
            spent += time.perf_counter() - t0
            calls += 1
            stored += len(batch)
            ids.append(res.identity_ids)
            if (i + 4) % every == 0 or i + 4 >= n:
                rows.append((i + 4, mem.stats()["identities"], 1000 * spent / calls, checked[0] / stored))
                spent, calls, stored, checked[0] = 0.0, 0, 0, 0
        return rows, np.concatenate(ids)
    finally:
        index_mod.GridIndex.resolve = orig


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--game", default="ALE/Freeway-v5", help="ALE game id")
    ap.add_argument("--transitions", type=int, default=6000, help="ALE steps played and stored")
    ap.add_argument("--dims", type=int, nargs="+", default=[3, 8], help="index_projection_dim values to compare")
    ap.add_argument("--every", type=int, default=1000, help="steps per printed row")
    ap.add_argument("--seed", type=int, default=0)
    add_blas_threads(ap)
    args = ap.parse_args()
    apply_blas_threads(args)
    t0 = time.perf_counter()
    t = play(args.game, args.transitions, args.seed)
    print(f"[bench] {args.transitions} {args.game} transitions played in {time.perf_counter() - t0:.1f} s", flush=True)
    results = {}
    for dims in args.dims:
        t0 = time.perf_counter()
        rows, ids = run(t, dims, args.every, args.seed)
        results[dims] = (rows, ids, time.perf_counter() - t0)
        print(f"[bench] dims {dims}: {results[dims][2]:.1f} s", flush=True)
    base = args.dims[0]
    for dims in args.dims[1:]:
        same = np.array_equal(results[dims][1], results[base][1])
        print(f"[bench] identity ids of dims {dims} equal those of dims {base}: {same}")
    print("\n| steps | identities | " + " | ".join(f"dims {d}: ms/store, re-checks/transition" for d in args.dims)
          + (f" | speed-up {args.dims[-1]} vs {base} |" if len(args.dims) > 1 else " |"))
    print("|---" * (2 + len(args.dims) + (len(args.dims) > 1)) + "|")
    for k, row in enumerate(results[base][0]):
        cells = [f"{results[d][0][k][2]:.1f}, {results[d][0][k][3]:.2f}" for d in args.dims]
        ratio = f" | {row[2] / results[args.dims[-1]][0][k][2]:.1f}x" if len(args.dims) > 1 else ""
        print(f"| {row[0]} | {row[1]} | " + " | ".join(cells) + ratio + " |")
    if len(args.dims) > 1:
        print(f"\ntotal store time: " + ", ".join(f"dims {d} {results[d][2]:.1f} s" for d in args.dims))


if __name__ == "__main__":
    main()
