#!/usr/bin/env python3
"""In-process benchmark of the compact-memory core (comper_memory.core).

For each key size (26, 770, 14114) and identity count, fills a CompactMemory with that many
distinct identities, then measures in the same run:
  * store throughput (batches of --batch transitions: half re-stores of stored transitions,
    half new ones) of CompactMemory vs (a) a brute-force faiss IndexFlatL2 search per batch
    over the same keys (search only, no float64 re-check, no bookkeeping);
  * sample throughput (k=--sample-k from RTM) vs (b) a plain numpy FIFO replay buffer;
  * memory per identity (CompactMemory.bytes_used() / identities) vs raw key bytes.

    python benchmarks/memory_core_bench.py --quick
    python benchmarks/memory_core_bench.py --sizes 26:1000000 14114:100000
"""
from __future__ import annotations

import argparse
import time

import faiss
import numpy as np

from comper_memory.core import CompactMemory, MemoryConfig, transition_keys
from comper_msgs_py.arrays import Transitions

from bench_args import add_blas_threads, apply_blas_threads

SHAPES = {26: ("float", (12,), 1), 770: ("float", (384,), 1), 14114: ("uint8", (84, 84), 0)}


def make(rng, n, key):
    kind, obs, adim = SHAPES[key]
    if kind == "uint8":
        s = rng.integers(0, 256, (n,) + obs, dtype=np.uint8)
        s2 = rng.integers(0, 256, (n,) + obs, dtype=np.uint8)
        a = rng.integers(0, 18, n)
    else:
        s = rng.random((n,) + obs, dtype=np.float32)
        s2 = rng.random((n,) + obs, dtype=np.float32)
        a = rng.random((n, adim), dtype=np.float32)
    return Transitions(s, a, rng.random(n, dtype=np.float32), s2, np.zeros(n, bool), np.zeros(n, bool),
                       value_labels=rng.random(n, dtype=np.float32))


class FifoBuffer:
    def __init__(self, cap, key):
        self.keys = np.zeros((cap, key), np.float32)
        self.labels = np.zeros(cap, np.float32)
        self.n = 0

    def add(self, k, v):
        m = len(k)
        self.keys[self.n:self.n + m] = k
        self.labels[self.n:self.n + m] = v
        self.n += m

    def sample(self, k, rng):
        idx = rng.choice(self.n, k, replace=False)
        return self.keys[idx], self.labels[idx]


def run(key, n_ident, args):
    rng = np.random.default_rng(0)
    cfg = MemoryConfig(rtm_capacity=max(n_ident * 2, 20000), tm_capacity=max(n_ident * 2, 20000),
                       max_store_batch=max(args.batch, min(args.fill_batch, n_ident)), delta=1e-4)
    fill_cap = cfg.max_store_batch
    mem = CompactMemory(cfg)
    mem.index_engine = args.engine  # None: by key size (the default memory's choice)
    fill = min(args.fill_batch, fill_cap)
    t0 = time.perf_counter()
    kept = []
    done = 0
    while done < n_ident:
        b = make(rng, min(fill, n_ident - done), key)
        mem.store(b)
        if len(kept) < 4:
            kept.append(b)
        done += len(b)
    fill_s = time.perf_counter() - t0
    mem.reduce(max_sets=n_ident)
    pool = Transitions.concatenate(kept)
    # store throughput: half duplicates of stored transitions, half new
    batches = []
    for _ in range(args.store_batches):
        half = args.batch // 2
        batches.append(Transitions.concatenate([pool.take(rng.integers(0, len(pool), half)),
                                                make(rng, args.batch - half, key)]))
    t0 = time.perf_counter()
    for b in batches:
        mem.store(b)
    store_s = time.perf_counter() - t0
    store_rate = args.batch * len(batches) / store_s
    # (a) brute-force faiss flat search per batch over the same number of keys (no copy of the
    # keys: faiss.knn on the memory's reconstructed keys)
    flat_rate = float("nan")
    if not args.no_flat:
        slots = mem.slots.slots_sorted
        flat = faiss.IndexFlatL2(key)
        for s in range(0, len(slots), 20000):
            flat.add(mem.slots.keys_of_slots(slots[s:s + 20000]))
        qs = [transition_keys(b) for b in batches[:max(1, args.flat_batches)]]
        t0 = time.perf_counter()
        for q in qs:
            flat.search(q, 1)
        flat_rate = args.batch * len(qs) / (time.perf_counter() - t0)
        del flat
    # sampling vs FIFO buffer
    srng = np.random.default_rng(1)
    t0 = time.perf_counter()
    for _ in range(args.sample_calls):
        mem.sample(args.sample_k, rng=srng)
    sample_rate = args.sample_calls / (time.perf_counter() - t0)
    fifo_n = min(n_ident, args.fifo_max)
    fifo = FifoBuffer(fifo_n, key)
    fifo.add(np.zeros((fifo_n, key), np.float32), np.zeros(fifo_n, np.float32))
    t0 = time.perf_counter()
    for _ in range(args.sample_calls):
        fifo.sample(args.sample_k, srng)
    fifo_rate = args.sample_calls / (time.perf_counter() - t0)
    st = mem.stats()
    per_ident = st["bytes_used"] / st["identities"]
    hist_bytes = 4 * cfg.history_length
    return {"key": key, "identities": st["identities"], "fill_tps": n_ident / fill_s,
            "store_tps": store_rate, "flat_tps": flat_rate, "sample_cps": sample_rate,
            "fifo_cps": fifo_rate, "bytes_per_id": per_ident, "raw_key_bytes": 4 * key,
            "ratio": (per_ident - hist_bytes) / (4 * key), "nlist": mem.index.nlist,
            "engine": getattr(mem.index, "engine", "ivf"), "ratio_hist": per_ident / (4 * key + hist_bytes)}


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--quick", action="store_true", help="small sizes only (10k identities)")
    ap.add_argument("--sizes", nargs="*", default=None,
                    help="KEY:IDENTITIES pairs (default: 26,770 at 10k/100k/1M; 14114 at 10k/100k)")
    ap.add_argument("--batch", type=int, default=1000, help="transitions per measured store batch")
    ap.add_argument("--fill-batch", type=int, default=10000, help="transitions per fill batch")
    ap.add_argument("--store-batches", type=int, default=20, help="measured store batches")
    ap.add_argument("--flat-batches", type=int, default=3, help="batches searched with IndexFlatL2")
    ap.add_argument("--no-flat", action="store_true", help="skip the IndexFlatL2 baseline")
    ap.add_argument("--sample-k", type=int, default=32, help="entries per sample call")
    ap.add_argument("--sample-calls", type=int, default=2000, help="measured sample calls")
    ap.add_argument("--fifo-max", type=int, default=100000, help="largest FIFO baseline buffer")
    ap.add_argument("--engine", choices=("grid", "ivf"), default=None,
                    help="force an index engine (default: the memory's choice by key size)")
    ap.add_argument("--threads", type=int, default=0, help="faiss OpenMP threads (0: faiss default)")
    add_blas_threads(ap)
    args = ap.parse_args()
    apply_blas_threads(args)
    if args.threads:
        faiss.omp_set_num_threads(args.threads)
    if args.sizes:
        sizes = [tuple(int(x) for x in s.split(":")) for s in args.sizes]
    elif args.quick:
        sizes = [(26, 10000), (770, 10000), (14114, 2000)]
    else:
        sizes = [(k, n) for k in (26, 770) for n in (10_000, 100_000, 1_000_000)] + \
                [(14114, 10_000), (14114, 100_000)]
    cols = ["key", "identities", "engine", "nlist", "fill_tps", "store_tps", "flat_tps", "sample_cps", "fifo_cps",
            "bytes_per_id", "raw_key_bytes", "ratio", "ratio_hist"]
    print(" | ".join(cols), flush=True)
    for key, n in sizes:
        r = run(key, n, args)
        print(" | ".join(f"{r[c]:.4g}" if isinstance(r[c], float) else str(r[c]) for c in cols), flush=True)


if __name__ == "__main__":
    main()
