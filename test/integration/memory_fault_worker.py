"""A client process for the memory fault-injection tests: stores, reduces (two-phase, commit in
reversed order) and snapshots continuously, and appends every *acknowledged* result to an
acknowledgement file (one JSON line each, flushed) until the node stops answering.

    python memory_fault_worker.py --node NAME --worker W --ack-file acks.jsonl
    python memory_fault_worker.py ... --count 20 --stores-only --checkpoint-after 4

--count N stops after N stores (exit 0); --stores-only stores and nothing else (one WAL record per
store: the log's sequence is the number of stores); --checkpoint-after J asks for one checkpoint
(snapshot "") after store J.
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
    p.add_argument("--count", type=int, default=0, help="stop after this many stores (0: until the node stops)")
    p.add_argument("--stores-only", action="store_true", help="no reductions, no snapshots")
    p.add_argument("--checkpoint-after", type=int, default=-1, help="one checkpoint after this store")
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
            while not args.count or j < args.count:
                reply = memory.store(make_batch(args.worker, j, args.batch))
                ack(op="store", j=j, ids=[int(i) for i in reply.identity_ids], seq=int(reply.wal_sequence))
                if j == args.checkpoint_after:
                    memory.snapshot("")
                    ack(op="checkpoint", after=j)
                if args.stores_only:
                    j += 1
                    continue
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
