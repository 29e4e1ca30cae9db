"""TM and RTM as two tables over the slot table, their selectors, and the remover.

* :class:`DenseSet` -- members in a dense array: O(1) add/remove and the uniform selector.
* :class:`TransitionTable` (TM) -- similar-transition sets waiting for reduction. FIFO selector
  on each set's ``tm_key`` (the store sequence at which it entered; smaller = older); the
  two-phase reduction takes the oldest sets out under a lease, and an expired lease puts its
  sets back at the front.
* :class:`ReducedTable` (RTM) -- reduced sets with the QT's prediction, sampled uniformly.
* :class:`Remover` -- above a capacity, evicts the least recently updated identities
  (smallest ``last_seq``) from both tables, the index and the slot table.

Not thread-safe: the memory holds the lock.
"""
from __future__ import annotations

from typing import Callable

import numpy as np

from .keys import sq_dist_matrix
from .similarity import SimilarityIndex
from .slots import SlotTable

__all__ = ["DenseSet", "TransitionTable", "ReducedTable", "Remover"]


class DenseSet:
    """Members (slots) in a dense array for O(1)-per-item uniform sampling; pos[slot] = index or -1."""

    def __init__(self) -> None:
        self.items = np.zeros(16, dtype=np.int32)
        self.n = 0
        self.pos = np.zeros(0, dtype=np.int32)

    def resize(self, cap: int) -> None:
        old = self.pos
        self.pos = np.full(cap, -1, dtype=np.int32)
        self.pos[:len(old)] = old

    def members(self) -> np.ndarray:
        return self.items[:self.n]

    def contains(self, slots: np.ndarray) -> np.ndarray:
        return self.pos[slots] >= 0

    def add(self, slots: np.ndarray) -> None:
        """Add unique slots that are not members."""
        k = len(slots)
        if not k:
            return
        if self.n + k > len(self.items):
            grown = np.zeros(max(len(self.items) + len(self.items) // 4, self.n + k), dtype=np.int32)
            grown[:self.n] = self.items[:self.n]
            self.items = grown
        self.items[self.n:self.n + k] = slots
        self.pos[slots] = np.arange(self.n, self.n + k)
        self.n += k

    def remove(self, slots: np.ndarray) -> None:
        """Remove slots (members or not; duplicates allowed) by swap-with-tail, vectorized."""
        slots = np.unique(slots)
        slots = slots[self.pos[slots] >= 0]
        k = len(slots)
        if not k:
            return
        newn = self.n - k
        p = self.pos[slots]
        holes = np.sort(p[p < newn])
        tail = self.items[newn:self.n]
        fillers = tail[self.pos[tail] >= 0]
        fillers = fillers[~np.isin(fillers, slots)]
        self.items[holes] = fillers
        self.pos[fillers] = holes
        self.pos[slots] = -1
        self.n = newn

    def sample(self, k: int, num_batches: int, rng: np.random.Generator) -> np.ndarray:
        """Uniform selector: num_batches independent draws of k distinct members, concatenated."""
        idx = (np.concatenate([rng.choice(self.n, size=k, replace=False) for _ in range(num_batches)])
               if k else np.zeros(0, np.int64))
        return self.items[idx]


class _Table:
    """A set of slots of the slot table, with the uniform selector."""

    def __init__(self, table: SlotTable):
        self.table = table
        self.set = DenseSet()
        table.on_grow.append(self.set.resize)

    @property
    def n(self) -> int:
        return self.set.n

    def members(self) -> np.ndarray:
        return self.set.members()

    def contains(self, slots: np.ndarray) -> np.ndarray:
        return self.set.contains(slots)

    def remove(self, slots: np.ndarray) -> None:
        self.set.remove(slots)

    def sample(self, k: int, num_batches: int, rng: np.random.Generator) -> np.ndarray:
        return self.set.sample(k, num_batches, rng)

    def restore(self, ids: np.ndarray) -> None:
        """Members from a snapshot's order (ids)."""
        self.set.add(self.table.slots_of(ids))

    def bytes_used(self) -> int:
        return self.set.items.nbytes + self.set.pos.nbytes


class TransitionTable(_Table):
    """TM: FIFO by ``tm_key`` with leases for the two-phase reduction."""

    def __init__(self, table: SlotTable):
        super().__init__(table)
        self.leases: dict[int, tuple[np.ndarray, float]] = {}   # reduction id -> (ids, deadline)

    def labels(self, slots: np.ndarray) -> np.ndarray:
        """What a TM sample carries as value label: each set's newest label."""
        return self.table.newest_labels(slots)

    def enter(self, slots: np.ndarray, keys: np.ndarray) -> None:
        """Sets that are not members join at the back, in the order of their keys (increasing)."""
        self.table.a["tm_key"][slots] = keys
        self.set.add(slots)

    def to_front(self, slots: np.ndarray) -> None:
        mem = self.set.members()
        front = int(self.table.a["tm_key"][mem].min()) if len(mem) else 0
        self.set.remove(slots)
        self.table.a["tm_key"][slots] = front - len(slots) + np.arange(len(slots))
        self.set.add(slots)

    def expire(self, clock: Callable[[], float]) -> None:
        """Void the leases past their deadline; their sets go back to the front of TM."""
        if not self.leases:
            return
        now = clock()
        for rid in [r for r, (_, dl) in self.leases.items() if dl <= now]:
            ids, _ = self.leases.pop(rid)
            slots = self.table.slots_of(ids)
            slots = slots[slots >= 0]
            slots = slots[self.table.a["lease"][slots] == rid]
            if not len(slots):
                continue
            self.table.a["lease"][slots] = -1
            self.to_front(slots)

    def lease(self, k: int, rid: int, deadline: float) -> tuple[np.ndarray, np.ndarray]:
        """FIFO selector: take the k (at most) oldest sets out of TM under lease ``rid``;
        returns their (slots, ids), oldest first."""
        a = self.table.a
        mem = self.set.members()
        k = min(k, len(mem))
        keys = a["tm_key"][mem] if len(mem) else np.zeros(0, np.int64)
        if 0 < k < len(mem):
            pick = np.argpartition(keys, k - 1)[:k]
        else:
            pick = np.arange(k)
        pick = pick[np.argsort(keys[pick], kind="stable")]
        slots = mem[pick].copy()
        ids = a["id"][slots].copy() if k else np.zeros(0, np.int64)
        self.leases[rid] = (ids, deadline)
        if k:
            self.set.remove(slots)
            a["lease"][slots] = rid
        return slots, ids

    def release(self, slots: np.ndarray, rid: int) -> None:
        """The sets of lease ``rid`` among ``slots`` are no longer leased."""
        lease = self.table.a["lease"]
        mine = lease[slots] == rid
        lease[slots[mine]] = -1

    def replay_membership(self, slots: np.ndarray, in_tm: np.ndarray, tm_key: np.ndarray) -> None:
        """Reproduce the TM state a logged commit saw (its begin is not logged)."""
        self.set.remove(slots[~in_tm])
        back = slots[in_tm]
        self.table.a["tm_key"][back] = tm_key[in_tm]
        self.set.add(back[~self.set.contains(back)])

    def snapshot_into(self, arrays: dict[str, np.ndarray]) -> None:
        """tm_key, lease and tm_order of a snapshot (``arrays`` from ``SlotTable.rows``): leases
        are not persisted, so leased sets that are not in TM go back to its front."""
        t, a = self.table, self.table.a
        slots = t.slots_sorted
        leased = slots[(a["lease"][slots] >= 0) & ~self.set.contains(slots)]
        tm_order = self.set.members()
        tm_key = arrays["tm_key"].copy()
        if len(leased):
            front = int(a["tm_key"][tm_order].min()) if len(tm_order) else 0
            pos = np.searchsorted(t.ids_sorted, a["id"][leased])
            tm_key[pos] = front - len(leased) + np.arange(len(leased))
            tm_order = np.concatenate([tm_order, leased])
        arrays["tm_key"] = tm_key
        arrays["lease"] = np.full(len(slots), -1, dtype=np.int64)
        arrays["tm_order"] = a["id"][tm_order]


class ReducedTable(_Table):
    """RTM: reduced sets and their prediction, uniform selector."""

    def labels(self, slots: np.ndarray) -> np.ndarray:
        """What an RTM sample carries as value label: the QT's prediction."""
        return self.table.a["rtm_pred"][slots]

    def upsert(self, slots: np.ndarray, preds: np.ndarray) -> None:
        self.table.a["rtm_pred"][slots] = preds
        self.set.add(slots[~self.set.contains(slots)])

    def snapshot_into(self, arrays: dict[str, np.ndarray]) -> None:
        arrays["rtm_order"] = self.table.a["id"][self.set.members()]


class Remover:
    """Evicts identities above ``rtm_capacity`` live identities by the ``removal`` rule (lru: least recently
    updated, fifo: oldest created, reservoir: a uniform sample of every identity created, coverage: where the keys
    are densest) and the least recently
    updated above ``tm_capacity`` TM sets. Every choice is a function of the memory's state (and, for the
    reservoir, of ``seed`` and the identity's id), so a replayed WAL evicts the same identities."""

    RULES = ("lru", "fifo", "reservoir", "coverage")
    #: coverage: candidates drawn per identity to evict (at least COVERAGE_MIN_CANDIDATES), and the most key values
    #: the reference sample may hold (2,048 identities of MuJoCo keys, ~300 of 4-frame Atari keys)
    COVERAGE_CANDIDATES, COVERAGE_MIN_CANDIDATES, COVERAGE_REF_VALUES, COVERAGE_MAX_REFS = 4, 64, 1 << 24, 2048
    #: distances on at most this many key dimensions (every k-th of a longer key: image keys)
    COVERAGE_MAX_DIMS = 1024

    def __init__(self, table: SlotTable, tm: TransitionTable, rtm: ReducedTable,
                 rtm_capacity: int, tm_capacity: int, removal: str = "lru", seed: int = 0):
        if removal not in self.RULES:
            raise ValueError(f"removal must be one of {', '.join(self.RULES)}, got {removal!r}")
        self.table, self.tm, self.rtm = table, tm, rtm
        self.rtm_capacity, self.tm_capacity = rtm_capacity, tm_capacity
        self.removal, self.seed = removal, int(seed)

    def enforce(self, index: SimilarityIndex, new_ids: np.ndarray = ()) -> int:
        """Evict down to both capacities after a store that created ``new_ids`` (ascending); returns the number
        of identities evicted."""
        over = self.table.n_live - self.rtm_capacity
        if over <= 0:
            ev = 0
        elif self.removal == "fifo":
            ev = self.evict(index, self.table.slots_sorted[:over])      # slots in the order of their ids
        elif self.removal == "reservoir":
            ev = self.evict(index, self.table.slots_of(self._reservoir_out(np.asarray(new_ids, np.int64))))
        elif self.removal == "coverage":
            ev = self.evict(index, self._densest(over, np.asarray(new_ids, np.int64), index.key_dim))
        else:
            ev = self._evict_oldest(index, self.table.slots_sorted, over)
        return ev + self._evict_oldest(index, self.tm.members(), self.tm.n - self.tm_capacity)

    def _reservoir_out(self, new_ids: np.ndarray) -> np.ndarray:
        """The ids algorithm R lets go when the store that created ``new_ids`` took the live identities ``over``
        the capacity: each new identity j (ids count identities created, from 0) in turn enters a full reservoir
        with probability capacity / (j + 1), in place of a member drawn uniformly, else leaves at once. Older
        identities above the capacity (a capacity lowered since) leave first, oldest first."""
        cap = self.rtm_capacity
        ids = self.table.ids_sorted
        old = ids[~np.isin(ids, new_ids)]           # the reservoir before this store, by id
        out = list(old[:max(0, len(old) - cap)].tolist())
        members = np.empty(cap, np.int64)            # the reservoir, filled to n
        n = min(len(old), cap)
        members[:n] = old[len(old) - n:]
        for j in new_ids.tolist():
            if n < cap:
                members[n] = j
                n += 1
                continue
            rng = np.random.default_rng([self.seed, j])
            if rng.random() * (j + 1) < cap:
                k = int(rng.integers(n))
                out.append(int(members[k]))
                members[k] = j
            else:
                out.append(j)
        return np.asarray(out, np.int64)        # as many as `over`: every identity above the capacity

    def _densest(self, over: int, new_ids: np.ndarray, key_dim: int) -> np.ndarray:
        """The ``over`` slots the coverage rule lets go: candidates drawn uniformly from the live identities
        (COVERAGE_CANDIDATES per identity to evict, at least COVERAGE_MIN_CANDIDATES), each with the squared
        distance of its key (as the index sees it) to the nearest of a uniform reference sample of live identities
        (up to COVERAGE_MAX_REFS, fewer for long keys; distances on every k-th dimension of keys longer than
        COVERAGE_MAX_DIMS, e.g. the pixels of stacked frames); the candidate with the nearest neighbour leaves, in
        turn, and a reference that left no longer counts as a neighbour. So identities leave where the keys are
        densest and the memory keeps its spread (de Bruin et al., JMLR 2018). Draws from ``seed`` and the first
        new id: a WAL replay evicts the same ones."""
        slots = self.table.slots_sorted
        n = len(slots)
        if over >= n:
            return slots.copy()
        rng = np.random.default_rng([self.seed, int(new_ids[0]) if len(new_ids) else int(self.table.ids_sorted[-1])])
        k = min(n, max(self.COVERAGE_MIN_CANDIDATES, self.COVERAGE_CANDIDATES * over))
        cand = np.sort(rng.choice(n, size=k, replace=False))
        r = min(n, self.COVERAGE_MAX_REFS, max(self.COVERAGE_MIN_CANDIDATES, self.COVERAGE_REF_VALUES // key_dim))
        refs = np.sort(rng.choice(n, size=r, replace=False))
        cols = slice(None, None, -(-key_dim // self.COVERAGE_MAX_DIMS))   # every k-th dimension of a long key
        d2 = sq_dist_matrix(self.table.keys_of_slots(slots[cand])[:, cols],
                            self.table.keys_of_slots(slots[refs])[:, cols])
        d2[cand[:, None] == refs[None, :]] = np.inf            # not its own neighbour
        out = np.zeros(k, bool)
        for _ in range(over):                                   # k >= over: over < n
            i = int(np.nanargmin(np.where(out, np.nan, d2.min(1))))
            out[i] = True
            d2[:, refs == cand[i]] = np.inf                     # gone: no longer anyone's neighbour
        return slots[cand[out]]

    def _evict_oldest(self, index: SimilarityIndex, slots: np.ndarray, over: int) -> int:
        if over <= 0:
            return 0
        ls = self.table.a["last_seq"][slots]
        pick = np.argpartition(ls, over - 1)[:over] if over < len(ls) else np.arange(len(ls))
        return self.evict(index, slots[pick])

    def evict(self, index: SimilarityIndex, slots: np.ndarray) -> int:
        slots = np.unique(slots)
        if not len(slots):
            return 0
        index.remove(self.table.a["id"][slots].copy())
        self.tm.remove(slots)
        self.rtm.remove(slots)
        self.table.remove(slots)
        return len(slots)
