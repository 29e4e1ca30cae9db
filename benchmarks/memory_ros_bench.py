#!/usr/bin/env python3
"""Compact memory through ROS 2 (memory_node in its own process) vs the in-process core.

In one run, on the same data (Hopper-like transitions: obs 11, action 3, key 26):
  core   comper_memory.core.CompactMemory in this process
  ros    `ros2 run comper_memory memory_node` in a separate process, driven by a standalone
         comper_memory.client.MemoryClient from this process (numpy in / numpy out: the
         conversions through comper_msgs_py.convert are included in every figure)
Measures store throughput (transitions/s, batches of --batch), sample latency p50/p95 (--k
entries from RTM per call, after a full reduction), and for the ROS path the floor of a service
round trip (~/get_stats, an empty request) and the per-call cost of conversion and rclpy
serialization of the store request / sample response. Targets: store >= 10,000 transitions/s,
sample p50 <= 2 ms.

    . ./env.sh && python benchmarks/memory_ros_bench.py
    python benchmarks/memory_ros_bench.py --batches 2000 --samples 3000 --json benchmarks/out/memory_ros.json
"""
from __future__ import annotations

import argparse
import json
import os
import random
import shutil
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

TARGET_STORE, TARGET_SAMPLE_P50_MS = 10_000.0, 2.0


def parse_args(argv=None):
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                formatter_class=argparse.RawDescriptionHelpFormatter, epilog=__doc__)
    p.add_argument("--batches", type=int, default=1000, help="store calls measured (default 1000)")
    p.add_argument("--batch", type=int, default=64, help="transitions per store call (default 64)")
    p.add_argument("--samples", type=int, default=2000, help="sample calls measured (default 2000)")
    p.add_argument("--k", type=int, default=64, help="entries per sample call, from RTM (default 64)")
    p.add_argument("--obs", type=int, default=11, help="observation size (Hopper: 11)")
    p.add_argument("--act", type=int, default=3, help="action size (Hopper: 3)")
    p.add_argument("--repeat", type=float, default=0.25,
                   help="fraction of each batch that re-stores earlier transitions (similarity hits)")
    p.add_argument("--warmup", type=int, default=20, help="unmeasured calls before each measurement")
    p.add_argument("--storage", action="store_true",
                   help="give both memories a storage_dir (write-ahead log, durability flush)")
    p.add_argument("--executor-threads", type=int, nargs="+", default=[1, 4],
                   help="memory_node executor_threads values to measure, one node each "
                        "(1: SingleThreadedExecutor, the node's default; 4: MultiThreadedExecutor)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--json", type=Path, help="also write the results here")
    return p.parse_args(argv)


def make_batches(args):
    """--warmup + --batches batches; a --repeat fraction of each re-stores (exact copies of)
    transitions of the last 50 batches, with fresh labels: similarity hits."""
    from comper_msgs_py.arrays import Transitions
    rng = np.random.default_rng(args.seed)
    out = []
    for i in range(args.batches + args.warmup):
        n = args.batch
        t = Transitions(rng.normal(size=(n, args.obs)).astype(np.float32),
                        rng.uniform(-1, 1, (n, args.act)).astype(np.float32),
                        rng.normal(size=n).astype(np.float32),
                        rng.normal(size=(n, args.obs)).astype(np.float32),
                        rng.random(n) < 0.01, np.zeros(n, bool),
                        value_labels=rng.normal(size=n).astype(np.float32))
        k = int(round(args.repeat * n)) if out else 0
        if k:
            recent = out[-50:]
            src = rng.integers(0, len(recent), k)
            row = rng.integers(0, n, k)
            for name in ("states", "actions", "rewards", "next_states", "terminated"):
                getattr(t, name)[:k] = np.stack([getattr(recent[b], name)[r] for b, r in zip(src, row)])
        out.append(t)
    return out


def pct(xs, q):
    return float(np.percentile(np.asarray(xs), q) * 1e3)


def bench_core(batches, args, storage_dir):
    from comper_memory.core import CompactMemory, MemoryConfig
    cfg = MemoryConfig(storage_dir=storage_dir or "")
    mem = CompactMemory(cfg, 2 * args.obs + args.act + 1)
    for b in batches[:args.warmup]:
        mem.store(b)
    t0 = time.perf_counter()
    for b in batches[args.warmup:]:
        mem.store(b)
    store_dt = time.perf_counter() - t0
    mem.reduce(max_sets=10**9)
    lat = []
    for _ in range(args.warmup):
        mem.sample(args.k)
    for _ in range(args.samples):
        t0 = time.perf_counter()
        mem.sample(args.k)
        lat.append(time.perf_counter() - t0)
    stats = mem.stats()
    mem.close()
    return {"store_tr_s": args.batches * args.batch / store_dt, "sample_p50_ms": pct(lat, 50),
            "sample_p95_ms": pct(lat, 95), "identities": stats["identities"], "rtm_size": stats["rtm_size"]}


class RemoteMemory:
    """memory_node in its own process (`ros2 run`), a standalone MemoryClient here."""

    def __init__(self, log_dir, storage_dir, executor_threads=4):
        from comper_memory.client import MemoryClient
        ros2 = shutil.which("ros2")
        if ros2 is None:
            sys.exit("no ros2 command on PATH: source env.sh first (. ./env.sh in the workspace root)")
        self.name = f"bench_memory_{os.getpid()}_{executor_threads}"
        self.log_path = Path(log_dir) / f"{self.name}.log"
        self._log = open(self.log_path, "wb")
        cmd = [ros2, "run", "comper_memory", "memory_node", "--ros-args", "-r", f"__node:={self.name}",
               "-p", "stats_period_s:=1.0", "-p", f"executor_threads:={executor_threads}"]
        if storage_dir:
            cmd += ["-p", f"storage_dir:={storage_dir}"]
        self.proc = subprocess.Popen(cmd + ["--log-level", "warn"], stdout=self._log, stderr=subprocess.STDOUT,
                                     start_new_session=True)
        self.client = MemoryClient.standalone(self.name, timeout=60.0)
        if not self.client.wait_for_service(60.0):
            self.close()
            sys.exit(f"memory node did not come up; its log:\n{self.log_path.read_text(errors='replace')}")

    def cpu_s(self) -> float:
        """CPU seconds used so far by the node process (user + system)."""
        try:
            fields = Path(f"/proc/{self.proc.pid}/stat").read_text().rsplit(")", 1)[1].split()
            return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")
        except OSError:
            return float("nan")

    def close(self):
        self.client.close()
        if self.proc.poll() is None:
            os.killpg(self.proc.pid, signal.SIGINT)
            try:
                self.proc.wait(timeout=10)
            except subprocess.TimeoutExpired:
                os.killpg(self.proc.pid, signal.SIGKILL)
                self.proc.wait()
        self._log.close()


def bench_ros(batches, args, log_dir, storage_dir, executor_threads):
    if storage_dir:
        storage_dir = f"{storage_dir}_{executor_threads}"
    remote = RemoteMemory(log_dir, storage_dir, executor_threads)
    m = remote.client
    try:
        for b in batches[:args.warmup]:
            m.store(b)
        cpu0, t0 = remote.cpu_s(), time.perf_counter()
        lat_store = []
        for b in batches[args.warmup:]:
            t1 = time.perf_counter()
            m.store(b)
            lat_store.append(time.perf_counter() - t1)
        store_dt = time.perf_counter() - t0
        store_cpu = remote.cpu_s() - cpu0
        m.reduce(max_sets=2**31 - 1)
        for _ in range(args.warmup):
            m.sample(args.k)
        lat = []
        cpu0 = remote.cpu_s()
        for _ in range(args.samples):
            t0 = time.perf_counter()
            m.sample(args.k)
            lat.append(time.perf_counter() - t0)
        sample_cpu = remote.cpu_s() - cpu0
        rt = []
        for _ in range(min(args.samples, 1000)):
            t0 = time.perf_counter()
            m.stats()
            rt.append(time.perf_counter() - t0)
        stats = m.stats()
    finally:
        remote.close()
    n = args.batches * args.batch
    return {"store_tr_s": n / store_dt, "store_call_p50_ms": pct(lat_store, 50),
            "node_cpu_us_per_store": 1e6 * store_cpu / args.batches,
            "sample_p50_ms": pct(lat, 50), "sample_p95_ms": pct(lat, 95),
            "node_cpu_us_per_sample": 1e6 * sample_cpu / args.samples,
            "get_stats_p50_ms": pct(rt, 50), "identities": stats["identities"], "rtm_size": stats["rtm_size"]}


def bench_conversions(batches, args):
    """Per-call cost (us) of the message path outside the core: numpy <-> message
    (comper_msgs_py.convert) and rclpy serialization, as the node and client pay it."""
    from rclpy.serialization import deserialize_message, serialize_message

    from comper_memory.core import CompactMemory, MemoryConfig
    from comper_msgs.srv import Sample, Store
    from comper_msgs_py.convert import batch_to_transitions, transitions_to_batch
    b = batches[0]
    mem = CompactMemory(MemoryConfig(), 2 * args.obs + args.act + 1)
    for x in batches[:50]:
        mem.store(x)
    mem.reduce(max_sets=10**9)
    sampled = mem.sample(min(args.k, mem.rtm_size)).transitions
    reps = 500

    def per_call(fn):
        fn()
        t0 = time.perf_counter()
        for _ in range(reps):
            fn()
        return 1e6 * (time.perf_counter() - t0) / reps

    req = Store.Request()
    transitions_to_batch(b, req.batch)
    raw_req = serialize_message(req)
    resp = Sample.Response()
    transitions_to_batch(sampled, resp.batch)
    raw_resp = serialize_message(resp)
    return {
        "store_request_bytes": len(raw_req), "sample_response_bytes": len(raw_resp),
        "numpy_to_msg_us": per_call(lambda: transitions_to_batch(b, Store.Request().batch)),
        "msg_to_numpy_us": per_call(lambda: batch_to_transitions(req.batch)),
        "serialize_store_us": per_call(lambda: serialize_message(req)),
        "deserialize_store_us": per_call(lambda: deserialize_message(raw_req, Store.Request)),
        "serialize_sample_us": per_call(lambda: serialize_message(resp)),
        "deserialize_sample_us": per_call(lambda: deserialize_message(raw_resp, Sample.Response)),
    }


def main(argv=None) -> int:
    args = parse_args(argv)
    os.environ.setdefault("ROS_DOMAIN_ID", str(random.SystemRandom().randint(101, 200)))
    os.environ.setdefault("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")
    os.environ.setdefault("OMP_NUM_THREADS", "1")
    import faiss
    faiss.omp_set_num_threads(1)  # what memory_node does (faiss_threads:=1), for a like-for-like core
    log_dir = tempfile.mkdtemp(prefix="memory_ros_bench_")
    load = os.getloadavg()[0]
    print(f"# memory_ros_bench: {' '.join(sys.argv)}  (python {sys.version.split()[0]}, {os.cpu_count()} cpus, "
          f"load {load:.1f}, ROS_DOMAIN_ID {os.environ['ROS_DOMAIN_ID']}, logs in {log_dir})")
    batches = make_batches(args)
    key = 2 * args.obs + args.act + 1
    print(f"# {args.batches} store calls x {args.batch} transitions (key {key}, {args.repeat:.0%} re-stores), "
          f"{args.samples} sample calls x {args.k} from RTM, storage {'on' if args.storage else 'off'}")
    core_dir = os.path.join(log_dir, "core_storage") if args.storage else ""
    ros_dir = os.path.join(log_dir, "ros_storage") if args.storage else ""
    core = bench_core(batches, args, core_dir)
    ros = {f"ros x{n}": bench_ros(batches, args, log_dir, ros_dir, n) for n in args.executor_threads}
    conv = bench_conversions(batches, args)
    hdr = f"{'path':<22} {'store tr/s':>11} {'sample p50 ms':>14} {'sample p95 ms':>14} {'get_stats p50 ms':>17}"
    print(hdr)
    print("-" * len(hdr))
    print(f"{'core (in-process)':<22} {core['store_tr_s']:>11.0f} {core['sample_p50_ms']:>14.3f} "
          f"{core['sample_p95_ms']:>14.3f} {'-':>17}")
    for n, r in zip(args.executor_threads, ros.values()):
        label = f"ros, {'multi' if n > 1 else 'single'}-threaded ({n})"
        print(f"{label:<22} {r['store_tr_s']:>11.0f} {r['sample_p50_ms']:>14.3f} {r['sample_p95_ms']:>14.3f} "
              f"{r['get_stats_p50_ms']:>17.3f}")
        assert r["identities"] == core["identities"], "the node and the core disagree"
    for n, r in zip(args.executor_threads, ros.values()):
        print(f"executor_threads {n}: ros/core store {r['store_tr_s'] / core['store_tr_s']:.2f}x, store call p50 "
              f"{r['store_call_p50_ms']:.2f} ms; node CPU per store {r['node_cpu_us_per_store']:.0f} us, "
              f"per sample {r['node_cpu_us_per_sample']:.0f} us")
    print(f"identities {core['identities']} (node and core agree); message path per call: numpy->msg "
          f"{conv['numpy_to_msg_us']:.0f} us, msg->numpy {conv['msg_to_numpy_us']:.0f} us, serialize store request "
          f"({conv['store_request_bytes']} B) {conv['serialize_store_us']:.0f} us, deserialize "
          f"{conv['deserialize_store_us']:.0f} us; sample response ({conv['sample_response_bytes']} B) "
          f"{conv['serialize_sample_us']:.0f} / {conv['deserialize_sample_us']:.0f} us")
    for n, r in zip(args.executor_threads, ros.values()):
        ok_store = r["store_tr_s"] >= TARGET_STORE
        ok_sample = r["sample_p50_ms"] <= TARGET_SAMPLE_P50_MS
        print(f"targets, executor_threads {n}: store >= {TARGET_STORE:,.0f} tr/s {'met' if ok_store else 'NOT met'}; "
              f"sample p50 <= {TARGET_SAMPLE_P50_MS} ms {'met' if ok_sample else 'NOT met'}")
    if args.json:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps({"argv": sys.argv, "load": load, "core": core, "ros": ros,
                                         "conversions": conv}, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
