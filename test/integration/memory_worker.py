#!/usr/bin/env python3
"""A learner-like client process for test_memory_node.py (run with sys.executable).

    memory_worker.py --node NAME --worker W --batches B --batch N --out result.json
        stores B batches of N distinct transitions (batch j of worker W: make_batch(W, j, N)),
        sampling from TM and reducing between stores; writes a JSON summary at the end.
    memory_worker.py --node NAME --worker W --batch N --ack-file acks.txt --continuous
        stores batches until a call fails (the node was killed) and appends the index of each
        acknowledged batch to acks.txt (flushed before the next store).

Every transition of every (worker, batch) is distinct (states[:, 0] holds a unique number, so
two of them are at squared distance >= 1 > delta); make_batch is deterministic, so the test
regenerates exactly what was stored.
"""
from __future__ import annotations

import argparse
import json
import sys

import numpy as np

from comper_msgs_py.arrays import Transitions

OBS, ACT = 11, 3   # Hopper-like: key = 2*11 + 3 + 1 = 26


def make_batch(worker: int, j: int, n: int, label_shift: float = 0.0) -> Transitions:
    rng = np.random.default_rng([worker, j])
    uid = worker * 1_000_000 + j * n + np.arange(n)
    states = rng.normal(size=(n, OBS)).astype(np.float32)
    states[:, 0] = uid.astype(np.float32)
    return Transitions(
        states=states, actions=rng.uniform(-1, 1, (n, ACT)).astype(np.float32),
        rewards=rng.normal(size=n).astype(np.float32),
        next_states=rng.normal(size=(n, OBS)).astype(np.float32),
        terminated=rng.random(n) < 0.05, truncated=np.zeros(n, bool),
        value_labels=(rng.normal(size=n) + label_shift).astype(np.float32),
        episode_ids=np.full(n, worker, np.uint64), steps=uid.astype(np.uint64), run_id=f"worker{worker}")


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--node", required=True)
    p.add_argument("--worker", type=int, required=True)
    p.add_argument("--batch", type=int, default=32)
    p.add_argument("--batches", type=int, default=20)
    p.add_argument("--out")
    p.add_argument("--ack-file")
    p.add_argument("--continuous", action="store_true")
    args = p.parse_args(argv)

    from comper_memory.client import MemoryClient, MemoryServiceError

    with MemoryClient.standalone(args.node, timeout=20.0) as memory:
        if not memory.wait_for_service(30.0):
            print(f"worker {args.worker}: memory node {args.node} not found", file=sys.stderr)
            return 2
        if args.continuous:
            with open(args.ack_file, "a") as acks:
                j = 0
                while True:
                    try:
                        memory.store(make_batch(args.worker, j, args.batch), timeout=3.0)
                    except (TimeoutError, MemoryServiceError) as exc:
                        print(f"worker {args.worker}: stopped after {j} batches: {exc}", file=sys.stderr)
                        return 0
                    acks.write(f"{j}\n")
                    acks.flush()
                    j += 1
        ids, samples = [], 0
        for j in range(args.batches):
            reply = memory.store(make_batch(args.worker, j, args.batch))
            assert reply.stored == args.batch
            ids.extend(int(i) for i in reply.identity_ids)
            if j % 2 or j >= 5:  # TM always has entries; RTM once this worker has reduced
                _, sids, _ = memory.sample(8, source="tm" if j % 2 else "rtm")
                samples += len(sids)
            if j % 5 == 4:
                memory.reduce(max_sets=50)
        with open(args.out, "w") as f:
            json.dump({"worker": args.worker, "identity_ids": ids, "samples": samples}, f)
    return 0


if __name__ == "__main__":
    sys.exit(main())
