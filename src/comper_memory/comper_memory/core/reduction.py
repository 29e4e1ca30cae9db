"""The two-phase reduction (method.md section 2): TM sets leased to the QT, predictions committed to RTM.

* begin: the oldest TM sets leave TM under a lease (:meth:`~.tables.TransitionTable.lease`),
  with what the QT reads of them: representatives, label histories, counts.
* commit: the QT's predictions for exactly the lease's identities (any order, finite) are put
  in the lease's order and upserted into RTM; sets stored into since the lease stay in TM.

:class:`Reduction` works on the slot table and the two tables; the memory around it holds the
lock, numbers the leases, logs each commit and keeps the counters. Not thread-safe.
"""
from __future__ import annotations

import numpy as np

from .results import LEASE_GONE, LeaseError, MemoryInputError, ReductionLease, empty_transitions
from .slots import SlotTable
from .tables import ReducedTable, TransitionTable

__all__ = ["Reduction"]


class Reduction:
    """Leases out of TM and commits into RTM over one slot table."""

    def __init__(self, slots: SlotTable, tm: TransitionTable, rtm: ReducedTable):
        self.slots, self.tm, self.rtm = slots, tm, rtm

    def lease(self, k: int, rid: int, deadline: float, schema: dict | None) -> ReductionLease:
        """Pop up to k oldest TM sets into lease ``rid`` (due back at ``deadline``)."""
        slots, ids = self.tm.lease(k, rid, deadline)
        if len(slots):
            hist, lens = self.slots.histories(slots)
            reps = self.slots.reps(slots, self.slots.newest_labels(slots))
            counts = self.slots.a["count"][slots].copy()
        else:
            hist, lens = np.zeros(0, np.float32), np.zeros(0, np.int64)
            reps = empty_transitions(schema)
            counts = np.zeros(0, np.int64)
        return ReductionLease(rid, ids, reps, hist.astype(np.float32), lens.astype(np.int64), counts, deadline)

    def check_commit(self, rid: int, identity_ids: np.ndarray, predictions: np.ndarray) -> dict[str, np.ndarray]:
        """The commit of lease ``rid`` as it is logged and applied: ids and float32 predictions in
        the lease's order, and each id's TM state now (``in_tm``, ``tm_key``: a replay restores
        them, since begin is not logged). LeaseError / MemoryInputError, nothing changed, if the
        lease is unknown, the ids differ from the lease's or a prediction is not finite."""
        if rid not in self.tm.leases:
            raise LeaseError(f"commit_reduce: reduction {rid} {LEASE_GONE}")
        lids, _ = self.tm.leases[rid]
        ids = np.asarray(identity_ids, dtype=np.int64).reshape(-1)
        preds = np.asarray(predictions)
        if len(ids) != len(lids) or not np.array_equal(np.sort(ids), np.sort(lids)):
            raise LeaseError(f"commit_reduce: identity_ids differ from those of lease {rid} "
                             f"({len(lids)} ids, any order; got {len(ids)})")
        if preds.shape != (len(ids),) or preds.dtype.kind not in "fiu":
            raise MemoryInputError(f"commit_reduce: predictions must have shape ({len(ids)},), "
                                   f"got {preds.shape} {preds.dtype}")
        preds = preds.astype(np.float32)
        if not np.isfinite(preds).all():
            raise MemoryInputError("commit_reduce: predictions hold NaN or Inf")
        # any order is accepted; the commit is applied (and logged) in the lease's order, so
        # the resulting state (RTM order, hence seeded samples) does not depend on it
        in_lease = np.argsort(lids, kind="stable")
        given = np.argsort(ids, kind="stable")
        ordered = np.empty_like(preds)
        ordered[in_lease] = preds[given]
        ids, preds = lids.copy(), ordered
        slots = self.slots.slots_of(ids)
        alive = slots >= 0
        in_tm = np.zeros(len(ids), dtype=bool)
        in_tm[alive] = self.tm.contains(slots[alive])
        tm_key = np.zeros(len(ids), dtype=np.int64)
        tm_key[alive] = self.slots.a["tm_key"][slots[alive]] if alive.any() else 0
        return {"ids": ids, "preds": preds, "in_tm": in_tm, "tm_key": tm_key}

    def apply(self, rid: int, ids: np.ndarray, preds: np.ndarray, in_tm: np.ndarray, tm_key: np.ndarray,
              replay: bool = False) -> int:
        """Upsert the live ones of ``ids`` into RTM and end lease ``rid``; the number upserted
        (evicted ids are skipped)."""
        slots = self.slots.slots_of(ids)
        alive = slots >= 0
        s = slots[alive]
        if len(s):
            self.rtm.upsert(s, preds[alive])
            self.tm.release(s, rid)
            if replay:  # begin is not logged: reproduce the TM state the commit saw
                self.tm.replay_membership(s, in_tm[alive], tm_key[alive])
        return int(alive.sum())
