"""Lost service answers under load: N client processes call one memory_node at a high rate for a bounded time
and count the calls that get no answer.

    . ./env.sh && ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST python benchmarks/memory_service_stress.py   # --help
    python benchmarks/memory_service_stress.py --storers 4 --samplers 1 --fresh 1 --duration 60 --udp

Localhost only. One ``ros2 run comper_memory memory_node`` with the rate limiter on (``--samples-per-insert``,
``--error-buffer``, ``--min-size``), so stores and samples are held back and retried like the actors and
the learner of ``comcact_node mode:=async``; then, each in its own process:

* ``--storers`` storer processes: store batches of ``--batch`` new transitions in a loop (an actor);
* ``--samplers`` sampler processes: sample ``--sample-k`` rows of TM in a loop (the learner; TM needs no reduction);
* ``--fresh`` fresh-client processes: create a standalone MemoryClient, wait_for_service, store one batch
  at once, close, again (the first call of a new client, test_repeated_sigterm_always_exits_cleanly).

Each call has ``--call-timeout`` seconds (a normal answer takes milliseconds; one that does not come in
that time is counted as lost) and rate-limited calls are retried by MemoryClient (1-50 ms backoff).
``--udp`` sets FASTDDS_BUILTIN_TRANSPORTS=UDPv4 for every process (what the actor fleet uses). The
node's log is scanned for rclpy's "failed to send response" warnings (the server dropped an answer).
Prints one line per process and a total; ``--json FILE`` writes them.
"""
from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from bench_args import stop_node

OBS, ACT = 11, 3


def batch(rng, n, uid0):
    from comper_msgs_py.arrays import Transitions
    s = rng.standard_normal((n, OBS)).astype(np.float32)
    s[:, 0] = uid0 + np.arange(n)           # distinct from every other transition of the run
    return Transitions(s, rng.uniform(-1, 1, (n, ACT)).astype(np.float32), rng.standard_normal(n).astype(np.float32),
                       rng.standard_normal((n, OBS)).astype(np.float32), np.zeros(n, bool), np.zeros(n, bool),
                       value_labels=rng.standard_normal(n).astype(np.float32))


def worker(args) -> int:
    """One client process: loop its role until --duration is over; print a JSON line of counts."""
    from comper_memory.client import MemoryClient
    from comper_msgs_py.service_client import ServiceTimeout
    rng = np.random.default_rng(args.index)
    counts = {"role": args.role, "index": args.index, "calls": 0, "answered": 0, "lost": 0, "lost_first": 0,
              "refused": 0, "held_back": 0, "rate_limited_waits": 0, "resent": 0, "clients": 0}
    uid = (args.index + 1) * 1_000_000     # exact in float32 and far below max_key_abs for up to 15 processes
    end = time.monotonic() + args.duration
    call_timeout, limit = args.call_timeout, args.duration + 30.0
    extra = {} if args.resend_s is None else {"resend_s": args.resend_s}   # (clients before re-sends: no flag)

    def one_call(memory, first=False):
        nonlocal uid
        try:
            if args.role == "sampler":
                memory.sample(args.sample_k, source="tm", timeout=call_timeout)
            else:
                memory.store(batch(rng, args.batch, uid), timeout=call_timeout)
                uid += args.batch
            counts["answered"] += 1
        except ServiceTimeout as exc:
            if "rate limiter" in str(exc):   # held back until the run ended: not a lost answer
                counts["held_back"] += 1
            else:
                counts["lost"] += 1
                counts["lost_first"] += int(first)
        except Exception as exc:  # noqa: BLE001 - a refusal (e.g. a sample larger than the memory)
            counts["refused"] += 1
            counts.setdefault("last_refusal", str(exc)[:200])
        counts["calls"] += 1

    if args.role == "fresh":
        while time.monotonic() < end:
            with MemoryClient.standalone(args.node, timeout=call_timeout, rate_limit_timeout=limit, **extra) as memory:
                counts["clients"] += 1
                if not memory.wait_for_service(30.0):
                    counts["refused"] += 1
                    continue
                one_call(memory, first=True)
                counts["resent"] += getattr(memory, "resent", 0)
    else:
        with MemoryClient.standalone(args.node, timeout=call_timeout, rate_limit_timeout=limit, **extra) as memory:
            counts["clients"] = 1
            if memory.wait_for_service(60.0):
                while time.monotonic() < end:
                    one_call(memory)
            counts["rate_limited_waits"] = memory.rate_limited_waits
            counts["resent"] = getattr(memory, "resent", 0)
    print(json.dumps(counts), flush=True)
    return 0


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--storers", type=int, default=4)
    ap.add_argument("--samplers", type=int, default=1)
    ap.add_argument("--fresh", type=int, default=1, help="processes that make a new client for every call")
    ap.add_argument("--duration", type=float, default=60.0, help="seconds each client process calls")
    ap.add_argument("--batch", type=int, default=64)
    ap.add_argument("--sample-k", type=int, default=256)
    ap.add_argument("--call-timeout", type=float, default=5.0, help="seconds after which an answer counts as lost")
    ap.add_argument("--resend-s", type=float, help="MemoryClient's resend_s (default: the client's own; 0 = never)")
    ap.add_argument("--samples-per-insert", type=float, default=4.0)
    ap.add_argument("--error-buffer", type=float, default=1024.0)
    ap.add_argument("--min-size", type=int, default=256)
    ap.add_argument("--udp", action="store_true", help="FASTDDS_BUILTIN_TRANSPORTS=UDPv4 in every process")
    ap.add_argument("--node-arg", action="append", default=[], help="extra -p NAME:=VALUE for the node")
    ap.add_argument("--json")
    # internal: one client process
    ap.add_argument("--role", choices=("storer", "sampler", "fresh"), help=argparse.SUPPRESS)
    ap.add_argument("--index", type=int, default=0, help=argparse.SUPPRESS)
    ap.add_argument("--node", help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    if args.role:
        return worker(args)

    ros2 = shutil.which("ros2")
    if ros2 is None:
        sys.exit("no ros2 command on PATH: source env.sh first")
    env = os.environ.copy()
    env.setdefault("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")
    if args.udp:
        env["FASTDDS_BUILTIN_TRANSPORTS"] = "UDPv4"
    out_dir = Path(tempfile.mkdtemp(prefix="memory_stress_"))
    name = f"memory_stress_{os.getpid()}"
    node_log = open(out_dir / "node.log", "wb")
    params = [f"samples_per_insert:={args.samples_per_insert}", f"rate_error_buffer:={args.error_buffer}",
              f"min_size_to_sample:={args.min_size}", "stats_period_s:=0.0", *args.node_arg]
    node = subprocess.Popen([ros2, "run", "comper_memory", "memory_node", "--ros-args", "-r", f"__node:={name}",
                             *sum((["-p", p] for p in params), [])],
                            stdout=node_log, stderr=subprocess.STDOUT, env=env, start_new_session=True)
    roles = ["storer"] * args.storers + ["sampler"] * args.samplers + ["fresh"] * args.fresh
    procs = []
    t0 = time.monotonic()
    try:
        for i, role in enumerate(roles):
            cmd = [sys.executable, __file__, "--role", role, "--index", str(i), "--node", name,
                   "--duration", str(args.duration), "--batch", str(args.batch), "--sample-k", str(args.sample_k),
                   "--call-timeout", str(args.call_timeout)]
            cmd += [] if args.resend_s is None else ["--resend-s", str(args.resend_s)]
            procs.append(subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=open(out_dir / f"{role}{i}.err", "wb"),
                                          env=env, text=True))
        rows = []
        for p in procs:
            out, _ = p.communicate(timeout=args.duration + 300)
            lines = [ln for ln in out.splitlines() if ln.startswith("{")]
            rows.append(json.loads(lines[-1]) if lines else {"role": "?", "error": f"exit {p.returncode}"})
    finally:
        for p in procs:
            if p.poll() is None:
                p.kill()
        stop_node(node, timeout=30)
        node_log.close()
    wall = time.monotonic() - t0
    dropped = (out_dir / "node.log").read_text(errors="replace").count("failed to send response")
    for r in rows:
        print(json.dumps(r))
    total = {k: sum(r.get(k, 0) for r in rows) for k in ("calls", "answered", "lost", "lost_first", "refused",
                                                          "held_back", "rate_limited_waits", "resent", "clients")}
    total.update(answers_dropped_by_server=dropped, wall_s=round(wall, 1), udp=args.udp, logs=str(out_dir))
    print("total", json.dumps(total))
    if args.json:
        Path(args.json).write_text(json.dumps({"args": vars(args), "rows": rows, "total": total}, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
