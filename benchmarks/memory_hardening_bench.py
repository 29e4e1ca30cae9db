"""Store latency of the compact memory with stationary, drifting and poisoned keys (issue 16).

    . ./env.sh && python benchmarks/memory_hardening_bench.py                 # in-process + ROS
    python benchmarks/memory_hardening_bench.py --no-ros --identities 20000   # in-process only

Keys are 26-d (Hopper-like: obs 11, action 3, reward): ``--calls`` store calls of 64 transitions
(``--new`` new ones, the rest re-stores of earlier ones) are timed one by one while the memory
grows through ``--identities`` (filled with batches of 1024 to ``identities - calls * new / 2``
first, so the timed calls are centred on it). Scenarios:

* stationary: every value N(0, 1);
* drifting: the first observation value is a step counter (it grows by one per transition, so
  keys leave the index's fitted extent all the time);
* poisoned: stationary, plus one transition whose key holds a value at the ``max_key_abs`` bound
  (1e8 by default; larger values are refused), stored first and alive for the whole run.

Then one store of 16,384 new transitions (26-d) into each filled memory. The ROS rows start
``ros2 run comper_memory memory_node`` (default parameters but ``store_chunk``) per scenario and
time the same calls through a standalone MemoryClient; during the big store a second client thread
calls ``~/get_stats`` in a loop and the longest wait is printed. ``--store-chunks 0,2048`` gives one
ROS row per value (0: the store in one turn of the executor, as before chunking). Ratios are against
the stationary row of the same path in the same run.

    python benchmarks/memory_hardening_bench.py --scenarios stationary --repeat 3 --store-chunks 0,2048

``--limits`` (in-process only) measures the index's limits instead (issue 57), each against the
normal store measured in the same run on a memory filled the same way (``--identities``):

* one store of 1,024 / 4,096 / 16,384 / 65,536 new transitions whose keys jump outside the fitted
  grid (every observation value + 1e6) against one of as many ordinary ones (the ratio stays
  near 1 and the time per transition flat when the cost is linear in the batch);
* ``--calls`` stores of 64 under ``max_key_abs`` 3e38 after one key value of 1e20 (and one of
  3e37) was stored first, against the same calls without it.

    python benchmarks/memory_hardening_bench.py --limits --repeat 3
"""
from __future__ import annotations

import argparse
import os
import shutil
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

import numpy as np

from bench_args import stop_node

from comper_msgs_py.arrays import Transitions

OBS, ACT = 11, 3


def make(rng, n, scenario, start):
    s = rng.standard_normal((n, OBS)).astype(np.float32)
    s2 = rng.standard_normal((n, OBS)).astype(np.float32)
    if scenario == "drifting":
        s[:, 0] = (start + np.arange(n)).astype(np.float32)
        s2[:, 0] = s[:, 0] + 1
    return Transitions(s, rng.uniform(-1, 1, (n, ACT)).astype(np.float32),
                       rng.standard_normal(n).astype(np.float32), s2, np.zeros(n, bool), np.zeros(n, bool),
                       value_labels=rng.standard_normal(n).astype(np.float32))


def workload(scenario, identities, calls, bound, new_per_call=16, seed=0):
    """(fill batches, timed batches of 64, big batch of 16384)."""
    rng = np.random.default_rng(seed)
    step = 0
    fill = []
    if scenario == "poisoned":
        p = make(rng, 1, "stationary", 0)
        p.states[0, 3] = np.float32(bound)
        fill.append(p)
    while sum(len(b) for b in fill) < identities - calls * new_per_call // 2:
        fill.append(make(rng, 1024, scenario, step))
        step += 1024
    pool = Transitions.concatenate(fill[-4:])
    timed = []
    for _ in range(calls):
        new = make(rng, new_per_call, scenario, step)
        step += new_per_call
        timed.append(Transitions.concatenate([new, pool.take(rng.integers(0, len(pool), 64 - new_per_call))]))
    big = make(rng, 16384, scenario, step)
    return fill, timed, big


def pct(x, q):
    return float(np.percentile(np.asarray(x) * 1e3, q))


def fill_and_time(store, fill, timed) -> list[float]:
    """Store the `fill` batches, then the `timed` ones one call each; the seconds of each timed call."""
    for b in fill:
        store(b)
    lat = []
    for b in timed:
        t0 = time.perf_counter()
        store(b)
        lat.append(time.perf_counter() - t0)
    return lat


def run_core(fill, timed, big):
    from comper_memory.core import CompactMemory, MemoryConfig
    mem = CompactMemory(MemoryConfig())
    lat = fill_and_time(mem.store, fill, timed)
    t0 = time.perf_counter()
    mem.store(big)
    big_s = time.perf_counter() - t0
    return {"p50": pct(lat, 50), "p99": pct(lat, 99), "big_s": big_s, "ids": mem.stats()["identities"]}


def run_ros(fill, timed, big, log_dir, tag, store_chunk=None):
    from comper_memory.client import MemoryClient
    ros2 = shutil.which("ros2")
    if ros2 is None:
        sys.exit("no ros2 command on PATH: source env.sh first")
    name = f"hardening_bench_{os.getpid()}_{tag}"
    log = open(Path(log_dir) / f"{name}.log", "wb")
    proc = subprocess.Popen([ros2, "run", "comper_memory", "memory_node", "--ros-args", "-r", f"__node:={name}",
                             "-p", "stats_period_s:=0.0", "--log-level", "warn"]
                            + ([] if store_chunk is None else ["-p", f"store_chunk:={store_chunk}"]),
                            stdout=log, stderr=subprocess.STDOUT, start_new_session=True)
    client = MemoryClient.standalone(name, timeout=120.0)
    other = MemoryClient.standalone(name, timeout=120.0)
    try:
        if not (client.wait_for_service(60.0) and other.wait_for_service(60.0)):
            sys.exit(f"memory node did not come up: {(Path(log_dir) / f'{name}.log').read_text()}")
        lat = fill_and_time(client.store, fill, timed)
        waits, done = [], threading.Event()

        def poll():
            while not done.is_set():
                t0 = time.perf_counter()
                other.stats()
                waits.append(time.perf_counter() - t0)

        th = threading.Thread(target=poll, daemon=True)
        th.start()
        time.sleep(0.05)
        t0 = time.perf_counter()
        client.store(big)
        big_s = time.perf_counter() - t0
        done.set()
        th.join()
        ids = client.stats()["identities"]
    finally:
        client.close()
        other.close()
        stop_node(proc, timeout=20)
        log.close()
    return {"p50": pct(lat, 50), "p99": pct(lat, 99), "big_s": big_s, "ids": ids,
            "other_max_ms": max(waits) * 1e3 if waits else float("nan")}


def shifted(t: Transitions, by: float) -> Transitions:
    return Transitions(t.states + np.float32(by), t.actions, t.rewards, t.next_states + np.float32(by),
                       t.terminated, t.truncated, value_labels=t.value_labels)


def filled_memory(identities, seed, **config):
    from comper_memory.core import CompactMemory, MemoryConfig
    mem = CompactMemory(MemoryConfig(**config))
    rng = np.random.default_rng(seed)
    while mem.stats()["identities"] < identities:
        mem.store(make(rng, 1024, "stationary", 0))
    return mem


def run_limits(args) -> int:
    """Issue 57: jumping batches of growing size and a huge key value under a raised max_key_abs."""
    sizes = (1024, 4096, 16384, 65536)
    big = dict(max_store_batch=65536)
    runs = {}
    for rnd in range(args.repeat):
        for n in sizes:
            for kind in ("normal", "jump"):
                mem = filled_memory(args.identities, 0, **big)
                batch = make(np.random.default_rng(100 + rnd), n, "stationary", 0)
                if kind == "jump":
                    batch = shifted(batch, 1e6)
                t0 = time.perf_counter()
                mem.store(batch)
                runs.setdefault((n, kind), []).append(time.perf_counter() - t0)
            print(f"round {rnd} store({n}) normal {runs[(n, 'normal')][-1]:.3f} s  jump "
                  f"{runs[(n, 'jump')][-1]:.3f} s", flush=True)
        for poison in (None, 1e20, 3e37):
            from comper_memory.core import CompactMemory, MemoryConfig
            mem = CompactMemory(MemoryConfig(max_key_abs=3e38))
            rng = np.random.default_rng(7)
            if poison is not None:
                p = make(rng, 1, "stationary", 0)
                p.states[0, 3] = np.float32(poison)
                mem.store(p)
            fill, timed, _ = workload("stationary", args.identities, args.calls, 1e8, args.new, seed=rnd)
            lat = fill_and_time(mem.store, fill, timed)
            runs.setdefault(("poison", poison), []).append((pct(lat, 50), pct(lat, 99)))
            print(f"round {rnd} max_key_abs 3e38, stored value {poison or 'none'}: store(64) p50 "
                  f"{pct(lat, 50):.2f} ms  p99 {pct(lat, 99):.2f} ms", flush=True)
    print(f"\n{args.identities} identities first (26-d keys, in-process, blas_threads 1), median of "
          f"{args.repeat} rounds\n")
    print("| store of | normal s | keys outside the grid s | ratio | outside, us per transition |")
    print("|---|---|---|---|---|")
    for n in sizes:
        a, b = float(np.median(runs[(n, "normal")])), float(np.median(runs[(n, "jump")]))
        print(f"| {n:,} | {a:.3f} | {b:.3f} | {b / a:.2f} | {b / n * 1e6:.1f} |")
    print()
    print("| max_key_abs 3e38, value stored first | store(64) p50 ms | p99 ms | p50 / none | p99 / none |")
    print("|---|---|---|---|---|")
    base = [float(np.median([r[k] for r in runs[("poison", None)]])) for k in (0, 1)]
    for poison in (None, 1e20, 3e37):
        r = [float(np.median([x[k] for x in runs[("poison", poison)]])) for k in (0, 1)]
        print(f"| {poison or 'none'} | {r[0]:.2f} | {r[1]:.2f} | {r[0] / base[0]:.2f} | {r[1] / base[1]:.2f} |")
    return 0


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--identities", type=int, default=20000)
    ap.add_argument("--calls", type=int, default=1000, help="timed store calls of 64 per scenario")
    ap.add_argument("--new", type=int, default=16, help="new transitions per timed call (the rest re-stores)")
    ap.add_argument("--no-ros", action="store_true", help="in-process core only")
    ap.add_argument("--store-chunks", default="",
                    help="comma-separated store_chunk values, one ROS row each (default: the node's default)")
    ap.add_argument("--scenarios", default="stationary,drifting,poisoned", help="comma-separated subset")
    ap.add_argument("--repeat", type=int, default=3,
                    help="rounds over all scenarios (interleaved); the table gives the median of each figure")
    ap.add_argument("--limits", action="store_true",
                    help="the index's limits (issue 57): jumping batches of 1k-64k, a huge value under "
                    "max_key_abs 3e38 (in-process; see the module docstring)")
    args = ap.parse_args(argv)
    from comper_memory.core import MemoryConfig
    bound = getattr(MemoryConfig(), "max_key_abs", 1e8)  # the same poison on code without the bound
    try:
        from comper_msgs_py.blas import set_numpy_blas_threads
        set_numpy_blas_threads(1)  # as the node (blas_threads 1)
        import faiss
        faiss.omp_set_num_threads(1)
    except Exception:  # noqa: BLE001 - speed setting only
        pass
    if args.limits:
        return run_limits(args)
    chunks = [int(c) for c in args.store_chunks.split(",") if c.strip()] or [None]
    paths = [("core", None)] + ([] if args.no_ros else
                                [("ros" if c is None else f"ros chunk {c}", c) for c in chunks])
    scenarios = [x for x in ("stationary", "drifting", "poisoned") if x in args.scenarios.split(",")]
    runs = {}
    log_dir = tempfile.mkdtemp(prefix="hardening_bench_")
    loads = {s: workload(s, args.identities, args.calls, bound, args.new)
             for s in scenarios}
    for rnd in range(args.repeat):
        for scenario, (fill, timed, big) in loads.items():
            for path, chunk in paths:
                r = run_core(fill, timed, big) if path == "core" else \
                    run_ros(fill, timed, big, log_dir, f"{scenario}{rnd}", chunk)
                runs.setdefault((path, scenario), []).append(r)
                print(f"[{path}] round {rnd} {scenario:10s} identities after {r['ids']:6d}  store(64) p50 "
                      f"{r['p50']:7.2f} ms  p99 {r['p99']:7.2f} ms  store(16384) {r['big_s']:6.3f} s"
                      + (f"  other client's longest wait {r['other_max_ms']:.0f} ms" if "other_max_ms" in r else ""),
                      flush=True)
    rows = {k: {f: float(np.median([r[f] for r in v])) for f in v[0]} for k, v in runs.items()}
    print()
    print(f"| path | keys | store(64) p50 ms | store(64) p99 ms | p99 / {scenarios[0]} | 16,384-transition store s |"
          + (" longest get_stats wait during it, ms |" if not args.no_ros else ""))
    print("|---|---|---|---|---|---|" + ("---|" if not args.no_ros else ""))
    for path, _ in paths:
        base = rows[(path, scenarios[0])]["p99"]
        for scenario in scenarios:
            r = rows[(path, scenario)]
            extra = f" {r['other_max_ms']:.0f} |" if "other_max_ms" in r else (" - |" if not args.no_ros else "")
            print(f"| {path} | {scenario} | {r['p50']:.2f} | {r['p99']:.2f} | {r['p99'] / base:.2f} | "
                  f"{r['big_s']:.3f} |{extra}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
