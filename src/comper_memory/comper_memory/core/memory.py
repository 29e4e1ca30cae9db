"""CompactMemory: identities, similar-transition sets, TM, RTM, two-phase reduction, sampling.

Operations follow method.md section 2. All per-identity data lives in preallocated growable
numpy arrays indexed by a slot; identity ids are int64, allocated in increasing order and never
reused (slots are). One lock protects the whole state, so the ROS node may call from a
multi-threaded executor.
"""
from __future__ import annotations

import glob
import logging
import os
import shutil
import threading
import time
from dataclasses import dataclass
from typing import Callable

import numpy as np

from comper_msgs_py.arrays import TransitionError, Transitions

from . import storage as st
from .config import MemoryConfig
from .index import SimilarityIndex, make_index

# Keys up to this many values use the sorted-cell grid engine, longer keys faiss IVF (see
# docs/memory.md for the measurements behind the choice). Speed only, never results.
from .keys import transition_keys

__all__ = ["CompactMemory", "MemoryInputError", "LeaseError", "StoreResult", "SampleResult",
           "ReductionLease", "CommitResult", "newest_label"]


class MemoryInputError(ValueError):
    """A request to the memory is invalid; nothing was changed."""


class LeaseError(MemoryInputError):
    """A reduction lease is unknown, already committed or expired; nothing was changed."""


@dataclass
class StoreResult:
    identity_ids: np.ndarray   # int64 [N]: identity each transition joined or created
    new_identities: int        # identities created by this store
    similarity_hits: int       # transitions that joined an existing (or same-batch) identity
    evicted: int               # identities evicted to respect the capacities
    wal_sequence: int


@dataclass
class SampleResult:
    transitions: Transitions   # representatives; value_labels = QT prediction (RTM) / newest label (TM)
    identity_ids: np.ndarray   # int64 [k]
    counts: np.ndarray         # int64 [k]: transitions that joined each identity
    source: str


@dataclass
class ReductionLease:
    reduction_id: int
    identity_ids: np.ndarray        # int64 [k], TM order (oldest first)
    representatives: Transitions    # value_labels = newest label of each set
    label_history: np.ndarray       # float32 [sum(history_lengths)], per set oldest -> newest
    history_lengths: np.ndarray     # int64 [k]
    counts: np.ndarray              # int64 [k]
    expires_at: float               # clock() time after which the lease is void

    def __len__(self) -> int:
        return int(self.identity_ids.shape[0])

    def histories(self) -> list[np.ndarray]:
        return np.split(self.label_history, np.cumsum(self.history_lengths)[:-1]) if len(self) else []


@dataclass
class CommitResult:
    reduction_id: int
    upserted: int   # RTM entries written
    skipped: int    # identities evicted while leased
    wal_sequence: int


def newest_label(lease: ReductionLease) -> np.ndarray:
    """Built-in predictor for users without a QT: each set's newest value label."""
    return lease.representatives.value_labels.astype(np.float32, copy=True)


class _DenseSet:
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

    def set_order(self, slots: np.ndarray) -> None:
        self.pos[self.items[:self.n]] = -1
        self.n = 0
        self.add(np.asarray(slots, dtype=np.int32))


_SLOT_FIELDS = ("id", "rewards", "terminated", "truncated", "episode_id", "hist", "hist_total",
                "count", "first_step", "last_step", "last_seq", "tm_key", "rtm_pred", "lease",
                "states", "next_states", "actions")


class CompactMemory:
    """The compact memory (see module docstring and docs/memory.md)."""

    def __init__(self, config: MemoryConfig | None = None, key_size: int | None = None, *,
                 clock: Callable[[], float] = time.monotonic,
                 log: Callable[[str], None] | None = None):
        """log(text): where start-up warnings go (a torn WAL tail dropped, leftovers of an
        interrupted snapshot, accepted WAL loss); default the ``comper_memory`` Python logger."""
        self.config = (config or MemoryConfig()).validate()
        self._log = log or logging.getLogger("comper_memory").warning
        self.expected_key_size = key_size
        # config.index_engine chooses; tests and benchmarks may force 'grid' | 'ivf' here
        self.index_engine: str | None = None
        self._clock = clock
        self._lock = threading.RLock()
        self._wal: st.WriteAheadLog | None = None
        self._reset_state()
        if self.config.storage_dir:
            self._open_storage()

    # ================================================================== state
    def _reset_state(self) -> None:
        c = self.config
        self.schema: dict | None = None   # obs_shape, obs_dtype, action_shape, action_dtype, key_size
        self.index: SimilarityIndex | None = None
        self.cap = 0
        self.a: dict[str, np.ndarray] = {}
        self.free: list[int] = []
        self.hi = 0                        # slots ever used (slots >= hi are fresh)
        # live ids (increasing) and their slots: growable buffers (1.25x), views below
        self._ids_buf = np.zeros(0, dtype=np.int64)
        self._slots_buf = np.zeros(0, dtype=np.int32)
        self._n_sorted = 0
        self.n_live = 0
        self.tm = _DenseSet()
        self.rtm = _DenseSet()
        self.leases: dict[int, tuple[np.ndarray, float]] = {}
        self.next_id = 0
        self.next_reduction_id = 1
        self.transitions_stored = 0
        self.similarity_hits = 0
        self.reductions = 0
        self.sets_reduced = 0
        self.evictions = 0
        self.wal_sequence = 0
        self.checkpoint_sequence = 0
        self.H = c.history_length

    def _init_schema(self, t: Transitions) -> None:
        discrete = t.actions.ndim == 1
        key = 2 * int(np.prod(t.obs_shape, dtype=np.int64)) + (1 if discrete else t.actions.shape[1]) + 1
        self.schema = {"obs_shape": tuple(int(x) for x in t.obs_shape), "obs_dtype": t.states.dtype.str,
                       "action_shape": () if discrete else (int(t.actions.shape[1]),),
                       "action_dtype": "<i8" if discrete else "<f4", "key_size": key}
        self.index = make_index(self.config, key, self, self.index_engine)

    # the index's KeySource
    def live_ids(self) -> np.ndarray:
        return self.ids_sorted

    def keys_of(self, ids: np.ndarray) -> np.ndarray:
        return self._keys_of_slots(self._slots_of(ids))

    def alive(self, ids: np.ndarray) -> np.ndarray:
        return self._slots_of(ids) >= 0

    def _field_spec(self) -> dict[str, tuple[tuple, np.dtype, object]]:
        s = self.schema
        return {
            "id": ((), np.int64, -1), "rewards": ((), np.float32, 0), "terminated": ((), bool, False),
            "truncated": ((), bool, False), "episode_id": ((), np.uint64, 0),
            "hist": ((self.H,), np.float32, 0),
            "count": ((), np.int64, 0), "first_step": ((), np.uint64, 0), "last_step": ((), np.uint64, 0),
            "last_seq": ((), np.int64, 0), "tm_key": ((), np.int64, 0), "rtm_pred": ((), np.float32, 0),
            "lease": ((), np.int32, -1),
            "states": (s["obs_shape"], np.dtype(s["obs_dtype"]), 0),
            "next_states": (s["obs_shape"], np.dtype(s["obs_dtype"]), 0),
            "actions": (tuple(s["action_shape"]), np.dtype(s["action_dtype"]), 0),
        }

    def _grow(self, need: int) -> None:
        if need <= self.cap:
            return
        new = max(need, self.cap + self.cap // 4, 1024)  # 1.25x: little slack
        for name, (shape, dtype, fill) in self._field_spec().items():
            arr = np.full((new,) + shape, fill, dtype=dtype)
            if name in self.a:
                arr[:self.cap] = self.a[name][:self.cap]
            self.a[name] = arr
        self.tm.resize(new)
        self.rtm.resize(new)
        self.cap = new

    @property
    def ids_sorted(self) -> np.ndarray:
        """Live identity ids, increasing (a view)."""
        return self._ids_buf[:self._n_sorted]

    @property
    def slots_sorted(self) -> np.ndarray:
        """Slots of :attr:`ids_sorted` (a view)."""
        return self._slots_buf[:self._n_sorted]

    def _set_sorted(self, ids: np.ndarray, slots: np.ndarray) -> None:
        self._ids_buf = np.ascontiguousarray(ids, dtype=np.int64)
        self._slots_buf = np.ascontiguousarray(slots, dtype=np.int32)
        self._n_sorted = len(ids)

    def _append_sorted(self, ids: np.ndarray, slots: np.ndarray) -> None:
        n, k = self._n_sorted, len(ids)
        if n + k > len(self._ids_buf):
            cap = max(n + k, n + n // 4, 1024)
            ib = np.zeros(cap, np.int64)
            sb = np.zeros(cap, np.int32)
            ib[:n], sb[:n] = self._ids_buf[:n], self._slots_buf[:n]
            self._ids_buf, self._slots_buf = ib, sb
        self._ids_buf[n:n + k] = ids
        self._slots_buf[n:n + k] = slots
        self._n_sorted = n + k

    def _alloc(self, k: int) -> np.ndarray:
        take = min(k, len(self.free))
        out = np.empty(k, dtype=np.int32)
        if take:
            out[:take] = self.free[len(self.free) - take:]
            del self.free[len(self.free) - take:]
        rest = k - take
        if rest:
            self._grow(self.hi + rest)
            out[take:] = np.arange(self.hi, self.hi + rest)
            self.hi += rest
        return out

    def _slots_of(self, ids: np.ndarray) -> np.ndarray:
        """Slots of ids (-1 where the id is not live)."""
        ids = np.asarray(ids, dtype=np.int64)
        pos = np.searchsorted(self.ids_sorted, ids)
        pos_c = np.minimum(pos, max(len(self.ids_sorted) - 1, 0))
        ok = (pos < len(self.ids_sorted)) & (self.ids_sorted[pos_c] == ids) if len(self.ids_sorted) else \
            np.zeros(len(ids), dtype=bool)
        return np.where(ok, self.slots_sorted[pos_c] if len(self.slots_sorted) else -1, -1)

    def _keys_of_slots(self, slots: np.ndarray) -> np.ndarray:
        a = self.a
        t = Transitions(a["states"][slots], a["actions"][slots], a["rewards"][slots],
                        a["next_states"][slots], a["terminated"][slots], a["truncated"][slots])
        return transition_keys(t, self.config.frame_scale)

    def _newest_labels(self, slots: np.ndarray) -> np.ndarray:
        a = self.a
        return a["hist"][slots, (a["count"][slots] - 1) % self.H]

    def _reps(self, slots: np.ndarray, labels: np.ndarray) -> Transitions:
        a = self.a
        return Transitions(a["states"][slots], a["actions"][slots], a["rewards"][slots],
                           a["next_states"][slots], a["terminated"][slots], a["truncated"][slots],
                           value_labels=labels.astype(np.float32), episode_ids=a["episode_id"][slots],
                           steps=a["first_step"][slots])

    # ================================================================== validation
    def _validate_store(self, t: Transitions, replay: bool = False) -> tuple[Transitions, np.ndarray]:
        if not isinstance(t, Transitions):
            raise MemoryInputError(f"store expects a Transitions batch, got {type(t).__name__}")
        n = len(t)
        if n == 0:
            raise MemoryInputError("store: empty batch")
        if n > self.config.max_store_batch:
            raise MemoryInputError(f"store: batch of {n} exceeds max_store_batch ({self.config.max_store_batch})")
        try:
            t.validate(require_labels=True, require_finite=True)
        except TransitionError as e:
            raise MemoryInputError(f"store: {e}") from None
        if not np.isfinite(t.rewards.astype(np.float64)).all():
            raise MemoryInputError("store: rewards hold NaN or Inf")
        discrete = t.actions.ndim == 1
        if discrete:
            if t.actions.dtype.kind not in "iuf" or (t.actions.dtype.kind == "f" and
                                                      not np.array_equal(t.actions, np.round(t.actions))):
                raise MemoryInputError("store: discrete actions must be integer-valued")
            actions = t.actions.astype(np.int64)
        else:
            if t.actions.dtype.kind not in "iuf":
                raise MemoryInputError(f"store: actions of dtype {t.actions.dtype} are not numeric")
            actions = t.actions.astype(np.float32)
        s = self.schema
        if s is not None:
            if tuple(t.obs_shape) != tuple(s["obs_shape"]) or t.states.dtype.str != s["obs_dtype"]:
                raise MemoryInputError(
                    f"store: observations {t.states.dtype}{list(t.obs_shape)} differ from the memory's "
                    f"{np.dtype(s['obs_dtype'])}{list(s['obs_shape'])}")
            if tuple(actions.shape[1:]) != tuple(s["action_shape"]):
                raise MemoryInputError(f"store: action shape {actions.shape[1:]} differs from the memory's "
                                       f"{tuple(s['action_shape'])}")
        key = 2 * int(np.prod(t.obs_shape, dtype=np.int64)) + (1 if discrete else actions.shape[1]) + 1
        expected = s["key_size"] if s is not None else self.expected_key_size
        if expected is not None and key != expected:
            raise MemoryInputError(f"store: key size {key} differs from the memory's key size {expected}")
        u64 = np.uint64
        clean = Transitions(
            np.ascontiguousarray(t.states), actions, t.rewards.astype(np.float32),
            np.ascontiguousarray(t.next_states), t.terminated.astype(bool), t.truncated.astype(bool),
            value_labels=t.value_labels.astype(np.float32),
            episode_ids=t.episode_ids.astype(u64) if t.episode_ids.size else np.zeros(n, u64),
            steps=t.steps.astype(u64) if t.steps.size else np.zeros(n, u64), run_id=t.run_id)
        keys = transition_keys(clean, self.config.frame_scale)
        if not np.isfinite(keys).all():
            raise MemoryInputError("store: keys hold NaN or Inf (values overflow float32)")
        bound = self.config.max_key_abs
        if not replay and keys.size:  # replay: the record was accepted under its own bound
            mag = np.abs(keys).max(axis=1)
            if float(mag.max()) > bound:
                i = int(np.argmax(mag > bound))
                j = int(np.argmax(np.abs(keys[i]) > bound))
                obs = int(np.prod(t.obs_shape, dtype=np.int64))
                part = ("state" if j < obs else "action" if j < key - obs - 1 else
                        "reward" if j == key - obs - 1 else "next_state")
                raise MemoryInputError(
                    f"store: transition {i} has key value {float(keys[i, j]):g} ({part}, key position "
                    f"{j}) beyond max_key_abs ({bound:g}); nothing of this batch was stored (raise "
                    f"max_key_abs or rescale the observations)")
        return clean, keys

    # ================================================================== store
    def store(self, t: Transitions) -> StoreResult:
        """Store a batch (thesis Algorithm 6), atomically; raise MemoryInputError on bad input."""
        with self._lock:
            self._expire_leases()
            clean, keys = self._validate_store(t)
            if self.schema is None:
                self._init_schema(clean)
            y = self.index.project(keys)
            res = self.index.resolve(keys, y)
            if self._wal is not None:
                self._wal.append(self.wal_sequence + 1, st.WAL_STORE, _t_to_arrays(clean))
            self.wal_sequence += 1
            out = self._apply_store(clean, y, res)
            self._maybe_checkpoint()
            return out

    def _apply_store(self, t: Transitions, y: np.ndarray, res) -> StoreResult:
        a = self.a
        n = len(t)
        creates = res.creates
        cidx = np.flatnonzero(creates)
        n_new = len(cidx)
        new_ids = self.next_id + np.arange(n_new, dtype=np.int64)
        self.next_id += n_new
        new_slots = self._alloc(n_new)
        a = self.a
        # target identity / slot for each transition
        tid = np.empty(n, dtype=np.int64)
        tslot = np.empty(n, dtype=np.int64)
        tid[cidx] = new_ids
        tslot[cidx] = new_slots
        ex = res.existing >= 0
        tid[ex] = res.existing[ex]
        tslot[ex] = self._slots_of(res.existing[ex])
        bj = res.batch >= 0
        tid[bj] = tid[res.batch[bj]]   # creators come before their joiners
        tslot[bj] = tslot[res.batch[bj]]
        # representatives of new identities
        if n_new:
            a["id"][new_slots] = new_ids
            for f_src, f_dst in (("states", "states"), ("next_states", "next_states"),
                                 ("actions", "actions"), ("rewards", "rewards"),
                                 ("terminated", "terminated"), ("truncated", "truncated"),
                                 ("episode_ids", "episode_id"), ("steps", "first_step")):
                a[f_dst][new_slots] = getattr(t, f_src)[cidx]
            a["count"][new_slots] = 0
            a["lease"][new_slots] = -1
            a["rtm_pred"][new_slots] = 0
            self._append_sorted(new_ids, new_slots)
            self.n_live += n_new
        # per-set updates, grouped by slot, in transition order
        seq = self.transitions_stored + np.arange(n, dtype=np.int64)
        order = np.argsort(tslot, kind="stable")
        ss = tslot[order]
        first = np.ones(n, dtype=bool)
        first[1:] = ss[1:] != ss[:-1]
        gstart = np.flatnonzero(first)
        gsize = np.diff(np.append(gstart, n))
        useg = ss[gstart]
        rank = np.arange(n) - np.repeat(gstart, gsize)
        gs_rep = np.repeat(gsize, gsize)
        keep = rank >= gs_rep - self.H
        tot = a["count"][ss] + rank
        a["hist"][ss[keep], tot[keep] % self.H] = t.value_labels[order][keep]
        a["count"][useg] += gsize
        last = gstart + gsize - 1
        a["last_seq"][useg] = seq[order][last]
        a["last_step"][useg] = t.steps[order][last]
        # TM: sets not in TM enter at the back, in order of their first transition of this batch
        enter = ~self.tm.contains(useg)
        if enter.any():
            fs = seq[order][gstart][enter]
            eslots = useg[enter]
            o = np.argsort(fs)
            a["tm_key"][eslots[o]] = fs[o]
            self.tm.add(eslots[o])
        self.transitions_stored += n
        hits = n - n_new
        self.similarity_hits += hits
        if n_new:
            self.index.add(new_ids, y[cidx])
        evicted = self._enforce_capacity()
        return StoreResult(tid, int(n_new), int(hits), int(evicted), self.wal_sequence)

    def _enforce_capacity(self) -> int:
        c = self.config
        ev = 0
        over = self.n_live - c.rtm_capacity
        if over > 0:
            ls = self.a["last_seq"][self.slots_sorted]
            pick = np.argpartition(ls, over - 1)[:over] if over < len(ls) else np.arange(len(ls))
            ev += self._evict(self.slots_sorted[pick])
        over = self.tm.n - c.tm_capacity
        if over > 0:
            mem = self.tm.members()
            ls = self.a["last_seq"][mem]
            pick = np.argpartition(ls, over - 1)[:over] if over < len(ls) else np.arange(len(ls))
            ev += self._evict(mem[pick].copy())
        return ev

    def _evict(self, slots: np.ndarray) -> int:
        slots = np.unique(slots)
        if not len(slots):
            return 0
        a = self.a
        ids = a["id"][slots].copy()
        self.index.remove(ids)
        self.tm.remove(slots)
        self.rtm.remove(slots)
        keep = ~np.isin(self.ids_sorted, ids)
        self._set_sorted(self.ids_sorted[keep], self.slots_sorted[keep])
        a["id"][slots] = -1
        a["lease"][slots] = -1
        self.free.extend(slots.tolist())
        self.n_live -= len(slots)
        self.evictions += len(slots)
        return len(slots)

    # ================================================================== reduction
    def _expire_leases(self) -> None:
        if not self.leases:
            return
        now = self._clock()
        for rid in [r for r, (_, dl) in self.leases.items() if dl <= now]:
            ids, _ = self.leases.pop(rid)
            slots = self._slots_of(ids)
            slots = slots[slots >= 0]
            slots = slots[self.a["lease"][slots] == rid]
            if not len(slots):
                continue
            self.a["lease"][slots] = -1
            self._to_front(slots)

    def _to_front(self, slots: np.ndarray) -> None:
        mem = self.tm.members()
        front = int(self.a["tm_key"][mem].min()) if len(mem) else 0
        self.tm.remove(slots)
        self.a["tm_key"][slots] = front - len(slots) + np.arange(len(slots))
        self.tm.add(slots)

    def begin_reduce(self, max_sets: int | None = None) -> ReductionLease:
        """Pop up to max_sets (default reduce_batch) oldest TM sets into a lease for the QT."""
        with self._lock:
            self._expire_leases()
            k = self.config.reduce_batch if max_sets is None else int(max_sets)
            if k < 0:
                raise MemoryInputError(f"begin_reduce: max_sets must be >= 0, got {k}")
            mem = self.tm.members()
            k = min(k, len(mem))
            keys = self.a["tm_key"][mem] if self.schema is not None else np.zeros(0, np.int64)
            if 0 < k < len(mem):
                pick = np.argpartition(keys, k - 1)[:k]
            else:
                pick = np.arange(k)
            pick = pick[np.argsort(keys[pick], kind="stable")]
            slots = mem[pick].copy()
            rid = self.next_reduction_id
            self.next_reduction_id += 1
            ids = self.a["id"][slots].copy() if k else np.zeros(0, np.int64)
            deadline = self._clock() + self.config.lease_timeout_s
            self.leases[rid] = (ids, deadline)
            if k:
                self.tm.remove(slots)
                self.a["lease"][slots] = rid
                lens = np.minimum(self.a["count"][slots], self.H)
                tot = self.a["count"][slots]
                ridx = np.repeat(np.arange(k), lens)
                off = np.arange(int(lens.sum())) - np.repeat(np.cumsum(lens) - lens, lens)
                pos = (np.repeat(tot - lens, lens) + off) % self.H
                hist = self.a["hist"][slots[ridx], pos]
                reps = self._reps(slots, self._newest_labels(slots))
                counts = self.a["count"][slots].copy()
            else:
                lens = np.zeros(0, np.int64)
                hist = np.zeros(0, np.float32)
                reps = None
                counts = np.zeros(0, np.int64)
            if reps is None:
                reps = _empty_transitions(self.schema)
            return ReductionLease(rid, ids, reps, hist.astype(np.float32), lens.astype(np.int64),
                                  counts, deadline)

    def commit_reduce(self, reduction_id: int, identity_ids: np.ndarray,
                      predictions: np.ndarray) -> CommitResult:
        """Upsert the lease's identities into RTM with the QT's predictions."""
        with self._lock:
            self._expire_leases()
            rid = int(reduction_id)
            if rid not in self.leases:
                raise LeaseError(f"commit_reduce: reduction {rid} is unknown, already committed or expired")
            lids, _ = self.leases[rid]
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
            slots = self._slots_of(ids)
            alive = slots >= 0
            in_tm = np.zeros(len(ids), dtype=bool)
            in_tm[alive] = self.tm.contains(slots[alive])
            tm_key = np.zeros(len(ids), dtype=np.int64)
            tm_key[alive] = self.a["tm_key"][slots[alive]] if alive.any() else 0
            if self._wal is not None:
                self._wal.append(self.wal_sequence + 1, st.WAL_COMMIT,
                                 {"ids": ids, "preds": preds, "in_tm": in_tm, "tm_key": tm_key})
            self.wal_sequence += 1
            del self.leases[rid]
            out = self._apply_commit(rid, ids, preds, in_tm, tm_key)
            self._maybe_checkpoint()
            return out

    def _apply_commit(self, rid, ids, preds, in_tm, tm_key, replay: bool = False) -> CommitResult:
        slots = self._slots_of(ids)
        alive = slots >= 0
        s = slots[alive]
        a = self.a
        if len(s):
            a["rtm_pred"][s] = preds[alive]
            self.rtm.add(s[~self.rtm.contains(s)])
            mine = a["lease"][s] == rid
            a["lease"][s[mine]] = -1
            if replay:  # begin is not logged: reproduce the TM state the commit saw
                self.tm.remove(s[~in_tm[alive]])
                back = s[in_tm[alive]]
                a["tm_key"][back] = tm_key[alive][in_tm[alive]]
                self.tm.add(back[~self.tm.contains(back)])
        self.reductions += 1
        self.sets_reduced += int(alive.sum())
        return CommitResult(rid, int(alive.sum()), int((~alive).sum()), self.wal_sequence)

    def reduce(self, predict_fn: Callable[[ReductionLease], np.ndarray] | None = None,
               max_sets: int | None = None) -> CommitResult:
        """begin_reduce + predict_fn(lease) (default: newest label) + commit_reduce."""
        lease = self.begin_reduce(max_sets)
        preds = (predict_fn or newest_label)(lease)
        return self.commit_reduce(lease.reduction_id, lease.identity_ids, preds)

    # ================================================================== sampling
    def sample(self, k: int, source: str = "rtm", *, rng: np.random.Generator | None = None,
               seed: int | None = None, allow_fewer: bool = False, num_batches: int = 1) -> SampleResult:
        """k distinct entries drawn uniformly from RTM (default) or TM.

        num_batches > 1: that many independent draws of k, concatenated (entries are distinct
        within each draw, not across draws); k * num_batches must not exceed max_sample_batch.
        k larger than the source: MemoryInputError, unless allow_fewer=True (then all entries,
        in random order)."""
        with self._lock:
            self._expire_leases()
            if source not in ("rtm", "tm"):
                raise MemoryInputError(f"sample: source must be 'rtm' or 'tm', got {source!r}")
            k, nb = int(k), max(1, int(num_batches))
            if k < 0 or k * nb > self.config.max_sample_batch:
                raise MemoryInputError(f"sample: k={k} x num_batches={nb} outside [0, max_sample_batch="
                                       f"{self.config.max_sample_batch}]")
            ds = self.rtm if source == "rtm" else self.tm
            if k > ds.n:
                if not allow_fewer:
                    raise MemoryInputError(f"sample: k={k} exceeds the {ds.n} entries of {source.upper()}")
                k = ds.n
            if self.schema is None:
                raise MemoryInputError("sample: the memory is empty")
            rng = rng if rng is not None else np.random.default_rng(seed)
            idx = (np.concatenate([rng.choice(ds.n, size=k, replace=False) for _ in range(nb)]) if k
                   else np.zeros(0, np.int64))
            slots = ds.items[idx]
            labels = self.a["rtm_pred"][slots] if source == "rtm" else self._newest_labels(slots)
            return SampleResult(self._reps(slots, labels), self.a["id"][slots].copy(),
                                self.a["count"][slots].copy(), source)

    # ================================================================== introspection
    @property
    def rtm_size(self) -> int:
        with self._lock:
            self._expire_leases()
            return self.rtm.n

    @property
    def tm_size(self) -> int:
        with self._lock:
            self._expire_leases()
            return self.tm.n

    @property
    def key_size(self) -> int | None:
        return self.schema["key_size"] if self.schema else self.expected_key_size

    def bytes_used(self) -> int:
        with self._lock:
            b = sum(arr.nbytes for arr in self.a.values())
            b += self.tm.items.nbytes + self.tm.pos.nbytes + self.rtm.items.nbytes + self.rtm.pos.nbytes
            b += self._ids_buf.nbytes + self._slots_buf.nbytes + 8 * len(self.free)
            if self.index is not None:
                b += self.index.bytes_used()
            return int(b)

    def stats(self) -> dict:
        with self._lock:
            self._expire_leases()
            n = self.transitions_stored
            return {
                "key_size": self.key_size or 0, "delta": self.config.delta,
                "identities": self.n_live, "tm_sets": self.tm.n, "rtm_size": self.rtm.n,
                "transitions_stored": n, "similarity_hits": self.similarity_hits,
                "hit_rate": self.similarity_hits / n if n else 0.0,
                "compaction_ratio": self.rtm.n / n if n else 0.0,
                "reductions": self.reductions, "sets_reduced": self.sets_reduced,
                "evictions": self.evictions, "bytes_used": self.bytes_used(),
                "wal_sequence": self.wal_sequence, "leases": len(self.leases),
            }

    # ================================================================== snapshots
    def _state_arrays(self) -> tuple[dict[str, np.ndarray], dict]:
        slots = self.slots_sorted
        arrays = {}
        if self.schema is not None:
            for name in _SLOT_FIELDS:  # snapshot format unchanged: hist_total == count, int64 lease
                src = "count" if name == "hist_total" else name
                arrays[name] = self.a[src][slots]
            # leased sets that are not in TM go back to its front (leases are not persisted)
            leased = slots[(self.a["lease"][slots] >= 0) & ~self.tm.contains(slots)]
            tm_order = self.tm.members()
            tm_key = arrays["tm_key"].copy()
            if len(leased):
                front = int(self.a["tm_key"][tm_order].min()) if len(tm_order) else 0
                pos = np.searchsorted(self.ids_sorted, self.a["id"][leased])
                tm_key[pos] = front - len(leased) + np.arange(len(leased))
                tm_order = np.concatenate([tm_order, leased])
            arrays["tm_key"] = tm_key
            arrays["lease"] = np.full(len(slots), -1, dtype=np.int64)
            arrays["tm_order"] = self.a["id"][tm_order]
            arrays["rtm_order"] = self.a["id"][self.rtm.members()]
        meta = {"schema": None if self.schema is None else
                {**self.schema, "obs_shape": list(self.schema["obs_shape"]),
                 "action_shape": list(self.schema["action_shape"])},
                "history_length": self.H, "delta": self.config.delta,
                "frame_scale": self.config.frame_scale,
                "counters": {k: int(getattr(self, k)) for k in (
                    "next_id", "next_reduction_id", "transitions_stored", "similarity_hits",
                    "reductions", "sets_reduced", "evictions", "wal_sequence")}}
        return arrays, meta

    def _restore(self, arrays: dict[str, np.ndarray], meta: dict) -> None:
        if meta.get("history_length") != self.H or meta.get("delta") != self.config.delta or \
                meta.get("frame_scale") != self.config.frame_scale:
            raise st.SnapshotError("snapshot was written with a different delta, frame_scale or "
                                   "history_length than this memory's configuration")
        sch = meta.get("schema")
        if sch is not None and self.expected_key_size is not None and sch["key_size"] != self.expected_key_size:
            raise st.SnapshotError(f"snapshot key size {sch['key_size']} differs from {self.expected_key_size}")
        self._check_counters(arrays, meta)
        self._reset_state()
        for k, v in meta["counters"].items():
            setattr(self, k, int(v))
        self.checkpoint_sequence = self.wal_sequence
        if sch is None:
            return
        sch = {**sch, "obs_shape": tuple(sch["obs_shape"]), "action_shape": tuple(sch["action_shape"])}
        t0 = Transitions(np.zeros((1,) + sch["obs_shape"], np.dtype(sch["obs_dtype"])),
                         np.zeros((1,) + sch["action_shape"], np.dtype(sch["action_dtype"])),
                         np.zeros(1, np.float32), np.zeros((1,) + sch["obs_shape"], np.dtype(sch["obs_dtype"])),
                         np.zeros(1, bool), np.zeros(1, bool))
        self._init_schema(t0)
        self.schema = sch
        ids = arrays["id"]
        n = len(ids)
        slots = self._alloc(n)
        for name in _SLOT_FIELDS:
            if name != "hist_total":  # equals count (kept in the snapshot for its format)
                self.a[name][slots] = arrays[name]
        self._set_sorted(ids.astype(np.int64), slots)
        self.n_live = n
        self.tm.add(self._slots_of(arrays["tm_order"]))
        self.rtm.add(self._slots_of(arrays["rtm_order"]))
        self.index.reindex()

    def export_state(self) -> tuple[dict[str, np.ndarray], dict]:
        """(arrays, meta) exactly as a snapshot would hold them (live identities ordered by id)."""
        with self._lock:
            return self._state_arrays()

    def save_snapshot(self, path: str) -> None:
        """Write the whole state to the snapshot directory ``path`` (atomic, checksummed)."""
        with self._lock:
            arrays, meta = self._state_arrays()
            st.write_snapshot(path, arrays, meta)

    def load_snapshot(self, path: str) -> None:
        """Replace the state by the snapshot at ``path``; refused (state untouched) if it is bad."""
        with self._lock:
            arrays, meta = st.read_snapshot(path)
            self._check_arrays(arrays)
            seq = self.wal_sequence
            self._restore(arrays, meta)
            if self._wal is not None:
                # the restore is an operation at the current log position: the new snapshot keeps
                # the sequence monotone, so the older log files it replaces are never replayed
                # over it after a kill between the snapshot and their deletion
                self.wal_sequence = max(seq, self.wal_sequence)
                self._checkpoint()

    @staticmethod
    def _check_counters(arrays: dict[str, np.ndarray], meta: dict) -> None:
        """The metadata must agree with the arrays (a hand-edited next_id would hand out ids that
        exist already; format-1 manifests carry no checksum of their own)."""
        c = meta.get("counters")
        names = ("next_id", "next_reduction_id", "transitions_stored", "similarity_hits",
                 "reductions", "sets_reduced", "evictions", "wal_sequence")
        if not isinstance(c, dict) or any(not isinstance(c.get(k), int) or c[k] < 0 for k in names):
            raise st.SnapshotError("snapshot counters are missing or negative")
        ids = arrays.get("id")
        if ids is not None and len(ids):
            if c["next_id"] <= int(ids.max()) or len(np.unique(ids)) != len(ids):
                raise st.SnapshotError(f"snapshot metadata next_id {c['next_id']} does not exceed the "
                                       f"largest identity id {int(ids.max())} (or ids repeat)")
            if c["transitions_stored"] < int(arrays["count"].sum()):
                raise st.SnapshotError("snapshot metadata transitions_stored is below the stored counts")

    @staticmethod
    def _check_arrays(arrays: dict[str, np.ndarray]) -> None:
        if not arrays:
            return
        missing = [f for f in _SLOT_FIELDS + ("tm_order", "rtm_order") if f not in arrays]
        if missing:
            raise st.SnapshotError(f"snapshot lacks arrays {missing}")
        n = len(arrays["id"])
        bad = [f for f in _SLOT_FIELDS if len(arrays[f]) != n]
        if bad:
            raise st.SnapshotError(f"snapshot arrays {bad} do not have {n} rows")

    # ================================================================== durability
    def _snapshot_dir(self) -> str:
        return os.path.join(self.config.storage_dir, "snapshot")

    def _wal_files(self) -> list[str]:
        return sorted(glob.glob(os.path.join(self.config.storage_dir, "wal-*.log")))

    def _open_storage(self) -> None:
        d = self.config.storage_dir
        os.makedirs(d, exist_ok=True)
        self._recover_snapshot_dir()
        if os.path.lexists(self._snapshot_dir()):
            arrays, meta = st.read_snapshot(self._snapshot_dir())
            self._check_arrays(arrays)
            self._restore(arrays, meta)
        self._replay_wal()
        files = self._wal_files()
        path = files[-1] if files else os.path.join(d, f"wal-{self.wal_sequence + 1:016d}.log")
        self._wal = st.WriteAheadLog(path, self.config.durability)

    def _recover_snapshot_dir(self) -> None:
        """Finish or undo a snapshot write that a kill interrupted (storage_dir only).

        A checkpoint writes ``snapshot.tmp-<pid>``, renames ``snapshot`` to ``snapshot.old-<pid>``,
        renames the new one into place and deletes the old one; the log files it makes redundant
        are deleted only after that. So: no ``snapshot`` but an old one -> the kill fell between
        the two renames, the old one (the last good snapshot) goes back into place and the log
        replays over it. Leftover tmp/old directories holding only snapshot files are removed;
        anything else with such a name is left alone (with a warning)."""
        snap = self._snapshot_dir()
        olds = sorted(glob.glob(glob.escape(snap) + ".old-*"))
        tmps = sorted(glob.glob(glob.escape(snap) + ".tmp-*"))
        if not os.path.lexists(snap) and olds:
            good = []
            for o in olds:
                try:
                    _, meta = st.read_snapshot(o)
                    good.append((int(meta["counters"]["wal_sequence"]), o))
                except (st.SnapshotError, KeyError, TypeError, ValueError):
                    continue
            if good:
                _, best = max(good)
                os.rename(best, snap)
                self._log(f"storage: the last snapshot write was interrupted; restored the previous "
                          f"snapshot {os.path.basename(best)} -> snapshot (the log replays over it)")
                olds.remove(best)
        for left in olds + tmps:
            if st.is_snapshot_dir(left) or (os.path.isdir(left) and not os.path.islink(left) and
                                            set(os.listdir(left)) <= {"manifest.json", "state.npz"}):
                st._remove_snapshot_dir(left)
                self._log(f"storage: removed {os.path.basename(left)}, left by an interrupted snapshot write")
            else:
                self._log(f"storage: {left} is not a snapshot leftover; left untouched")

    def _replay_wal(self) -> None:
        """Replay every log file after the snapshot: loud about damage, never silently lossy."""
        files = self._wal_files()
        for i, path in enumerate(files):
            scan = st.scan_wal(path)
            last = i == len(files) - 1
            damaged = scan.damage == "corrupt" or (scan.damage == "torn" and not last)
            later = files[i + 1:]
            if damaged:
                later_records = sum(len(st.scan_wal(p).records) for p in later)
                if not self.config.wal_accept_loss:
                    more = (f" {later_records} more records are in {len(later)} later log files."
                            if later else "")
                    raise scan.corrupt_error(
                        f"{more} To start anyway and lose the damaged record and everything after "
                        f"it, restart once with -p wal_accept_loss:=true (MemoryConfig("
                        f"wal_accept_loss=True)); the damaged file is then copied to "
                        f"{os.path.basename(path)}.damaged-{scan.good_end} first.")
            for seq, kind, arr in scan.records:
                if seq <= self.wal_sequence:
                    continue
                if seq != self.wal_sequence + 1:
                    raise st.SnapshotError(f"WAL {path}: record {seq} follows {self.wal_sequence} (gap)")
                self._replay(seq, kind, arr)
            if damaged:
                keep = f"{path}.damaged-{scan.good_end}"
                shutil.copy2(path, keep)
                st.truncate_wal(path, scan.good_end)
                for p in later:
                    os.rename(p, p + ".discarded")
                self._log(f"storage: wal_accept_loss: dropped the damaged record at byte offset "
                          f"{scan.good_end} of {path} and {scan.records_after} intact records after it"
                          f"{f' plus {len(later)} later log files (renamed *.discarded)' if later else ''}; "
                          f"the damaged file is kept as {keep}; replayed up to sequence {self.wal_sequence}")
                return
            if scan.damage == "torn":
                st.truncate_wal(path, scan.good_end)
                self._log(f"storage: dropped a torn last record of {path} ({scan.size - scan.good_end} "
                          f"bytes at offset {scan.good_end}: the process stopped while writing it, so "
                          f"it was never acknowledged); replayed up to sequence {self.wal_sequence}")

    def _replay(self, seq: int, kind: int, arr: dict[str, np.ndarray]) -> None:
        if kind == st.WAL_STORE:
            t = _arrays_to_t(arr)
            clean, keys = self._validate_store(t, replay=True)
            if self.schema is None:
                self._init_schema(clean)
            y = self.index.project(keys)
            res = self.index.resolve(keys, y)
            self.wal_sequence = seq
            self._apply_store(clean, y, res)
        elif kind == st.WAL_COMMIT:
            self.wal_sequence = seq
            self.next_reduction_id += 1
            self._apply_commit(-1, arr["ids"], arr["preds"], arr["in_tm"], arr["tm_key"], replay=True)
        else:
            raise st.SnapshotError(f"WAL record {seq}: unknown kind {kind}")

    def _maybe_checkpoint(self) -> None:
        every = self.config.snapshot_every
        if self._wal is not None and every and self.wal_sequence - self.checkpoint_sequence >= every:
            self._checkpoint()

    def _checkpoint(self) -> None:
        """Snapshot into storage_dir, then rotate the WAL (older files are deleted)."""
        arrays, meta = self._state_arrays()
        st.write_snapshot(self._snapshot_dir(), arrays, meta)
        old = self._wal_files()
        self._wal.close()
        self._wal = st.WriteAheadLog(os.path.join(self.config.storage_dir,
                                                  f"wal-{self.wal_sequence + 1:016d}.log"),
                                     self.config.durability)
        for p in old:
            if p != self._wal.path:
                os.remove(p)
        self.checkpoint_sequence = self.wal_sequence

    def checkpoint(self) -> None:
        with self._lock:
            if self._wal is None:
                raise MemoryInputError("checkpoint: storage_dir is not set")
            self._checkpoint()

    def close(self) -> None:
        with self._lock:
            if self._wal is not None:
                self._wal.close()
                self._wal = None

    def __enter__(self) -> "CompactMemory":
        return self

    def __exit__(self, *exc) -> None:
        self.close()


_T_FIELDS = ("states", "actions", "rewards", "next_states", "terminated", "truncated",
             "value_labels", "episode_ids", "steps")


def _t_to_arrays(t: Transitions) -> dict[str, np.ndarray]:
    return {f: getattr(t, f) for f in _T_FIELDS}


def _arrays_to_t(arr: dict[str, np.ndarray]) -> Transitions:
    return Transitions(**{f: arr[f] for f in _T_FIELDS})


def _empty_transitions(schema: dict | None) -> Transitions:
    if schema is None:
        return Transitions(np.zeros((0, 0), np.float32), np.zeros(0, np.int64), np.zeros(0, np.float32),
                           np.zeros((0, 0), np.float32), np.zeros(0, bool), np.zeros(0, bool),
                           value_labels=np.zeros(0, np.float32))
    obs = (0,) + tuple(schema["obs_shape"])
    return Transitions(np.zeros(obs, np.dtype(schema["obs_dtype"])),
                       np.zeros((0,) + tuple(schema["action_shape"]), np.dtype(schema["action_dtype"])),
                       np.zeros(0, np.float32), np.zeros(obs, np.dtype(schema["obs_dtype"])),
                       np.zeros(0, bool), np.zeros(0, bool), value_labels=np.zeros(0, np.float32),
                       episode_ids=np.zeros(0, np.uint64), steps=np.zeros(0, np.uint64))
