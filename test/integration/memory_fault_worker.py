"""A client process for the memory fault-injection tests: stores, reduces (two-phase, commit in
reversed order) and snapshots continuously, and appends every *acknowledged* result to an
acknowledgement file (one JSON line each, flushed) until the node stops answering.

    python memory_fault_worker.py --node NAME --worker W --ack-file acks.jsonl
"""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from memory_worker import make_batch  # noqa: E402


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--node", required=True)
    p.add_argument("--worker", type=int, required=True)
    p.add_argument("--batch", type=int, default=16)
    p.add_argument("--ack-file", required=True)
    args = p.parse_args(argv)

    from comper_memory.client import MemoryClient, MemoryServiceError

    with MemoryClient.standalone(args.node, timeout=2.0) as memory, open(args.ack_file, "a") as acks:
        if not memory.wait_for_service(30.0):
            print(f"worker {args.worker}: memory node {args.node} not found", file=sys.stderr)
            return 2

        def ack(**rec):
            acks.write(json.dumps(rec) + "\n")
            acks.flush()

        j = 0
        try:
            while True:
                reply = memory.store(make_batch(args.worker, j, args.batch))
                ack(op="store", j=j, ids=[int(i) for i in reply.identity_ids])
                if j % 3 == 2:
                    sets = memory.reduce_begin(max_sets=8)
                    ids = sets.identity_ids[::-1].copy()
                    preds = (ids % 97).astype("float32")
                    memory.reduce_commit(sets.reduction_id, ids, preds)
                    ack(op="commit", ids=[int(i) for i in ids], preds=[float(x) for x in preds])
                if j % 5 == 4:
                    memory.snapshot("")                       # checkpoint + WAL rotation
                    ack(op="checkpoint")
                if j % 7 == 6:
                    memory.snapshot(f"named-{args.worker}-{j % 2}")  # a named snapshot, replaced
                    ack(op="named")
                j += 1
        except (TimeoutError, MemoryServiceError, RuntimeError) as exc:
            print(f"worker {args.worker}: stopped after {j} batches: {type(exc).__name__}: {exc}",
                  file=sys.stderr)
    return 0


if __name__ == "__main__":
    sys.exit(main())
