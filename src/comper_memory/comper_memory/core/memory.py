"""CompactMemory: identities, similar-transition sets, TM, RTM, two-phase reduction, sampling.

Operations follow method.md section 2. The memory composes its parts and holds the one lock
that protects them all (the ROS node may call from a multi-threaded executor):

* :class:`~.slots.SlotTable` -- per-identity columns, id <-> slot map, keys for the index;
* :class:`~.tables.TransitionTable` (TM, FIFO with leases) and :class:`~.tables.ReducedTable`
  (RTM, uniform), with the :class:`~.tables.Remover` that enforces the capacities;
* the similarity index (:func:`~.index.make_index`), which decides what each stored
  transition joins;
* :class:`~.durability.Durability` -- WAL, snapshots, recovery (when ``storage_dir`` is set).

Every operation is validated whole first (:mod:`.validation`), then logged, then applied, so
a refused request changes nothing and a replayed log rebuilds the same state.
"""
from __future__ import annotations

import logging
import threading
import time
import weakref
from collections import OrderedDict
from typing import Callable

import numpy as np

from comper_msgs_py.arrays import Transitions

from . import storage as st
from .config import MemoryConfig
from .rate_limiter import RateLimited, RateLimiter
from .durability import COUNTERS, Durability, arrays_to_t, check_arrays, check_counters, t_to_arrays
from .index import make_index
from .results import (CommitResult, LeaseError, MemoryInputError, ReductionLease, SampleResult,
                      StoreResult, empty_transitions, newest_label)
from .similarity import ResolveResult, SimilarityIndex
from .slots import SlotTable
from .tables import ReducedTable, Remover, TransitionTable
from .validation import index_key_size, schema_of, validate_store

__all__ = ["CompactMemory", "ChunkedStore", "MemoryInputError", "LeaseError", "StoreResult", "SampleResult",
           "ReductionLease", "CommitResult", "newest_label"]


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
        self._durable: Durability | None = None
        self._closed = False
        # chunked stores not yet fully applied (a restore waits for them: ChunkedStore)
        self._stores_in_progress: weakref.WeakSet = weakref.WeakSet()
        # answers of stores with a request id (re-sent stores): id -> finished ChunkedStore, oldest first
        self._answers: OrderedDict[int, ChunkedStore] = OrderedDict()
        self._answers_size = 0
        self._pending_ids: dict[int, ChunkedStore] = {}
        self._reset_state()
        c = self.config
        self.rate = RateLimiter(c.min_size_to_sample, c.samples_per_insert, c.rate_error_buffer)
        if self.config.storage_dir:
            self._durable = Durability(self.config, self._log, state=self._state_arrays,
                                       sequence=lambda: self.wal_sequence)
            self._durable.open(self._restore, self._replay)
            self.rate.recovered(self.slots.n_live)

    # ================================================================== parts
    def _reset_state(self) -> None:
        c = self.config
        self.schema: dict | None = None   # obs_shape, obs_dtype, action_shape, action_dtype, key_size
        self.index: SimilarityIndex | None = None
        self.slots = SlotTable(c.history_length, c.frame_scale)
        self.a = self.slots.a   # the slot columns (one dict for the table's life; tests read it)
        self._keys_of_slots = self.slots.keys_of_slots   # (benchmarks read it)
        self.tm = TransitionTable(self.slots)
        self.rtm = ReducedTable(self.slots)
        self.remover = Remover(self.slots, self.tm, self.rtm, c.rtm_capacity, c.tm_capacity)
        for name in COUNTERS:
            setattr(self, name, 0)
        self.next_reduction_id = 1

    def _init_schema(self, schema: dict) -> None:
        self.schema = schema
        self.slots.schema = schema
        key = index_key_size(schema["obs_shape"], schema["action_shape"])
        self.index = make_index(self.config, key, self.slots, self.index_engine)

    # views of the slot table that tests and benchmarks read
    @property
    def ids_sorted(self) -> np.ndarray:
        return self.slots.ids_sorted

    @property
    def slots_sorted(self) -> np.ndarray:
        return self.slots.slots_sorted

    # ================================================================== store
    def store(self, t: Transitions, request_id: int = 0) -> StoreResult:
        """Store a batch (thesis Algorithm 6), atomically; raise MemoryInputError on bad input.
        request_id (0 = none): see :meth:`begin_store`."""
        return self.begin_store(t, chunk=0, request_id=request_id).result()

    def begin_store(self, t: Transitions, chunk: int = 0, request_id: int = 0) -> "ChunkedStore":
        """Validate a whole batch, admit it to the rate limiter and apply its first ``chunk``
        transitions (0: all of them), under one hold of the lock; :meth:`ChunkedStore.step`
        applies the rest, one chunk per call, each under its own hold of the lock.

        Bad input raises MemoryInputError (RateLimited when held back) before anything changes.
        Each chunk is one logged store (its own WAL record and sequence number), so between
        chunks other calls see the chunks applied so far, and a recovered memory replays exactly
        what was applied, in the order it was. The result equals one store of the whole batch
        (decisions are "as if sequential", ids allocated in order) unless a capacity evicts
        between chunks or other stores interleave (docs/memory-service.md, "Large batches").

        request_id > 0: the client's id of this batch. A store with the id of one still in progress
        or remembered (``resend_window``) is not applied again: it returns that store (``repeated``
        True; step it like any other), before validation and the rate limiter."""
        with self._lock:
            rid = int(request_id)
            if rid > 0 and self.config.resend_window > 0:
                same = self._pending_ids.get(rid) or self._answers.get(rid)
                if same is not None:
                    return same.repeat()
            self.tm.expire(self._clock)
            clean, keys = validate_store(t, self.config, self.schema, self.expected_key_size)
            self.rate.check_insert(len(clean), self.slots.n_live)
            if self.schema is None:
                self._init_schema(schema_of(clean))
            op = ChunkedStore(self, clean, keys, int(chunk) if chunk and chunk > 0 else len(clean), rid)
            op._step_locked()
            self.rate.inserted(len(clean))   # admitted whole: later chunks are not checked again
            if op.done:
                self._finished(op)
            else:
                self._stores_in_progress.add(op)
                if rid > 0 and self.config.resend_window > 0:
                    self._pending_ids[rid] = op
            return op

    def _finished(self, op: "ChunkedStore") -> None:
        """A store is fully applied (the lock is held): remember its answer by its request id."""
        self._stores_in_progress.discard(op)
        rid = op.request_id
        if rid <= 0 or self.config.resend_window <= 0:
            return
        self._pending_ids.pop(rid, None)
        self._answers[rid] = op
        self._answers_size += op.n
        while self._answers_size > self.config.resend_window and len(self._answers) > 1:
            _, old = self._answers.popitem(last=False)
            self._answers_size -= old.n

    def _store_chunk(self, clean: Transitions, keys: np.ndarray) -> StoreResult:
        """One logged store of a validated batch (the lock is held)."""
        y = self.index.project(keys)
        res = self.index.resolve(keys, y)
        if self._durable is not None:
            self._durable.append(self.wal_sequence + 1, st.WAL_STORE, t_to_arrays(clean))
        self.wal_sequence += 1
        out = self._apply_store(clean, y, res)
        if self._durable is not None:
            self._durable.maybe_checkpoint()
        return out

    def _apply_store(self, t: Transitions, y: np.ndarray, res: ResolveResult) -> StoreResult:
        n = len(t)
        cidx = np.flatnonzero(res.creates)
        n_new = len(cidx)
        new_ids = self.next_id + np.arange(n_new, dtype=np.int64)
        self.next_id += n_new
        new_slots = self.slots.create(new_ids, t, cidx)
        # target identity / slot for each transition
        tid = np.empty(n, dtype=np.int64)
        tslot = np.empty(n, dtype=np.int64)
        tid[cidx] = new_ids
        tslot[cidx] = new_slots
        ex = res.existing >= 0
        tid[ex] = res.existing[ex]
        tslot[ex] = self.slots.slots_of(res.existing[ex])
        bj = res.batch >= 0
        tid[bj] = tid[res.batch[bj]]   # creators come before their joiners
        tslot[bj] = tslot[res.batch[bj]]
        useg, first_seq = self.slots.record(tslot, t.value_labels, t.steps, self.transitions_stored)
        # TM: sets not in TM enter at the back, in order of their first transition of this batch
        enter = ~self.tm.contains(useg)
        if enter.any():
            fs = first_seq[enter]
            o = np.argsort(fs)
            self.tm.enter(useg[enter][o], fs[o])
        self.transitions_stored += n
        hits = n - n_new
        self.similarity_hits += hits
        if n_new:
            self.index.add(new_ids, y[cidx])
        evicted = self.remover.enforce(self.index)
        self.evictions += evicted
        return StoreResult(tid, int(n_new), int(hits), int(evicted), self.wal_sequence)

    # ================================================================== reduction
    def begin_reduce(self, max_sets: int | None = None) -> ReductionLease:
        """Pop up to max_sets (default reduce_batch) oldest TM sets into a lease for the QT."""
        with self._lock:
            self.tm.expire(self._clock)
            k = self.config.reduce_batch if max_sets is None else int(max_sets)
            if k < 0:
                raise MemoryInputError(f"begin_reduce: max_sets must be >= 0, got {k}")
            rid = self.next_reduction_id
            self.next_reduction_id += 1
            deadline = self._clock() + self.config.lease_timeout_s
            slots, ids = self.tm.lease(k, rid, deadline)
            if len(slots):
                hist, lens = self.slots.histories(slots)
                reps = self.slots.reps(slots, self.slots.newest_labels(slots))
                counts = self.a["count"][slots].copy()
            else:
                hist, lens = np.zeros(0, np.float32), np.zeros(0, np.int64)
                reps = empty_transitions(self.schema)
                counts = np.zeros(0, np.int64)
            return ReductionLease(rid, ids, reps, hist.astype(np.float32), lens.astype(np.int64),
                                  counts, deadline)

    def commit_reduce(self, reduction_id: int, identity_ids: np.ndarray,
                      predictions: np.ndarray) -> CommitResult:
        """Upsert the lease's identities into RTM with the QT's predictions."""
        with self._lock:
            self.tm.expire(self._clock)
            rid = int(reduction_id)
            if rid not in self.tm.leases:
                raise LeaseError(f"commit_reduce: reduction {rid} is unknown, already committed or expired")
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
            tm_key[alive] = self.a["tm_key"][slots[alive]] if alive.any() else 0
            if self._durable is not None:
                self._durable.append(self.wal_sequence + 1, st.WAL_COMMIT,
                                     {"ids": ids, "preds": preds, "in_tm": in_tm, "tm_key": tm_key})
            self.wal_sequence += 1
            del self.tm.leases[rid]
            out = self._apply_commit(rid, ids, preds, in_tm, tm_key)
            if self._durable is not None:
                self._durable.maybe_checkpoint()
            return out

    def _apply_commit(self, rid, ids, preds, in_tm, tm_key, replay: bool = False) -> CommitResult:
        slots = self.slots.slots_of(ids)
        alive = slots >= 0
        s = slots[alive]
        if len(s):
            self.rtm.upsert(s, preds[alive])
            self.tm.release(s, rid)
            if replay:  # begin is not logged: reproduce the TM state the commit saw
                self.tm.replay_membership(s, in_tm[alive], tm_key[alive])
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
            self.tm.expire(self._clock)
            if source not in ("rtm", "tm"):
                raise MemoryInputError(f"sample: source must be 'rtm' or 'tm', got {source!r}")
            k, nb = int(k), max(1, int(num_batches))
            if k < 0 or k * nb > self.config.max_sample_batch:
                raise MemoryInputError(f"sample: k={k} x num_batches={nb} outside [0, max_sample_batch="
                                       f"{self.config.max_sample_batch}]")
            self.rate.check_sample(k * nb, self.slots.n_live)   # before the size checks: a sampler may wait to fill
            table = self.rtm if source == "rtm" else self.tm
            if k > table.n:
                if not allow_fewer:
                    raise MemoryInputError(f"sample: k={k} exceeds the {table.n} entries of {source.upper()}")
                k = table.n
            if self.schema is None:
                raise MemoryInputError("sample: the memory is empty")
            rng = rng if rng is not None else np.random.default_rng(seed)
            slots = table.sample(k, nb, rng)
            self.rate.sampled(k * nb)
            return SampleResult(self.slots.reps(slots, table.labels(slots)), self.a["id"][slots].copy(),
                                self.a["count"][slots].copy(), source)

    # ================================================================== introspection
    @property
    def rtm_size(self) -> int:
        with self._lock:
            self.tm.expire(self._clock)
            return self.rtm.n

    @property
    def tm_size(self) -> int:
        with self._lock:
            self.tm.expire(self._clock)
            return self.tm.n

    @property
    def key_size(self) -> int | None:
        return self.schema["key_size"] if self.schema else self.expected_key_size

    def bytes_used(self) -> int:
        with self._lock:
            b = self.slots.bytes_used() + self.tm.bytes_used() + self.rtm.bytes_used()
            if self.index is not None:
                b += self.index.bytes_used()
            return int(b)

    def stats(self) -> dict:
        with self._lock:
            self.tm.expire(self._clock)
            n = self.transitions_stored
            return {
                "key_size": self.key_size or 0, "delta": self.config.delta,
                "identities": self.slots.n_live, "tm_sets": self.tm.n, "rtm_size": self.rtm.n,
                "transitions_stored": n, "similarity_hits": self.similarity_hits,
                "hit_rate": self.similarity_hits / n if n else 0.0,
                "compaction_ratio": self.rtm.n / n if n else 0.0,
                "reductions": self.reductions, "sets_reduced": self.sets_reduced,
                "evictions": self.evictions, "bytes_used": self.bytes_used(),
                "wal_sequence": self.wal_sequence, "leases": len(self.tm.leases),
            }

    def rate_stats(self) -> dict:
        """The rate limiter's counts (RateLimiter.stats): of this process's life, not the memory's state."""
        with self._lock:
            return self.rate.stats()

    # ================================================================== snapshots
    def _state_arrays(self) -> tuple[dict[str, np.ndarray], dict]:
        arrays = {}
        if self.schema is not None:
            arrays = self.slots.rows()
            self.tm.snapshot_into(arrays)
            self.rtm.snapshot_into(arrays)
        meta = {"schema": None if self.schema is None else
                {**self.schema, "obs_shape": list(self.schema["obs_shape"]),
                 "action_shape": list(self.schema["action_shape"])},
                "history_length": self.config.history_length, "delta": self.config.delta,
                "frame_scale": self.config.frame_scale,
                "counters": {k: int(getattr(self, k)) for k in COUNTERS}}
        return arrays, meta

    def _restore(self, arrays: dict[str, np.ndarray], meta: dict) -> None:
        c = self.config
        if meta.get("history_length") != c.history_length or meta.get("delta") != c.delta or \
                meta.get("frame_scale") != c.frame_scale:
            raise st.SnapshotError("snapshot was written with a different delta, frame_scale or "
                                   "history_length than this memory's configuration")
        sch = meta.get("schema")
        if sch is not None and self.expected_key_size is not None and sch["key_size"] != self.expected_key_size:
            raise st.SnapshotError(f"snapshot key size {sch['key_size']} differs from {self.expected_key_size}")
        check_counters(arrays, meta)
        self._reset_state()
        for k, v in meta["counters"].items():
            setattr(self, k, int(v))
        if sch is None:
            return
        self._init_schema({**sch, "obs_shape": tuple(sch["obs_shape"]),
                           "action_shape": tuple(sch["action_shape"])})
        self.slots.load_rows(arrays)
        self.tm.restore(arrays["tm_order"])
        self.rtm.restore(arrays["rtm_order"])
        self.index.reindex()

    def _replay(self, seq: int, kind: int, arr: dict[str, np.ndarray]) -> None:
        """Apply one logged operation (recovery)."""
        if kind == st.WAL_STORE:
            clean, keys = validate_store(arrays_to_t(arr), self.config, self.schema,
                                         self.expected_key_size, replay=True)
            if self.schema is None:
                self._init_schema(schema_of(clean))
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
            if any(not op.done for op in self._stores_in_progress):
                raise MemoryInputError("restore: a large store is being applied in chunks; restore once "
                                       "it is answered (a restore would replace the state under it)")
            arrays, meta = st.read_snapshot(path)
            check_arrays(arrays)
            seq = self.wal_sequence
            self._restore(arrays, meta)
            self._answers.clear()   # they describe the replaced state
            self._answers_size = 0
            self.rate.recovered(self.slots.n_live)
            if self._durable is not None:
                # the restore is an operation at the current log position: the new snapshot keeps
                # the sequence monotone, so the older log files it replaces are never replayed
                # over it after a kill between the snapshot and their deletion
                self.wal_sequence = max(seq, self.wal_sequence)
                self._durable.checkpoint()

    # ================================================================== durability
    def checkpoint(self) -> None:
        with self._lock:
            if self._durable is None:
                raise MemoryInputError("checkpoint: storage_dir is not set")
            self._durable.checkpoint()

    def close(self) -> None:
        with self._lock:
            self._closed = True
            if self._durable is not None:
                self._durable.close()
                self._durable = None

    def __enter__(self) -> "CompactMemory":
        return self

    def __exit__(self, *exc) -> None:
        self.close()


class ChunkedStore:
    """A validated store being applied chunk by chunk (:meth:`CompactMemory.begin_store`).

    ``step()`` applies the next chunk under the memory's lock and returns ``done``; between two
    steps the lock is free, so other calls run. ``result()`` applies whatever is left and returns
    the StoreResult of the whole batch. After the memory is closed a step raises
    MemoryInputError (nothing more is applied or logged); ``applied`` says how many transitions
    are in the memory then."""

    def __init__(self, memory: CompactMemory, clean: Transitions, keys: np.ndarray, chunk: int,
                 request_id: int = 0):
        self._memory = memory
        self._t, self._keys, self.chunk = clean, keys, max(1, int(chunk))
        self.n = len(clean)
        self.request_id = int(request_id)
        self.applied = 0
        self._parts: list[StoreResult] = []

    #: True on what a re-sent store gets (:meth:`repeat`): this store, not applied again
    repeated = False

    def repeat(self) -> "ChunkedStore":
        """This store as a re-send of it sees it: the same progress, steps and result, ``repeated``."""
        return _Repeated(self)

    @property
    def done(self) -> bool:
        return self.applied >= self.n

    @property
    def chunks(self) -> int:
        return -(-self.n // self.chunk)

    def step(self) -> bool:
        """Apply the next chunk (no-op once done); True when the whole batch is applied."""
        if self.done:
            return True
        m = self._memory
        with m._lock:
            if not self.done:
                self._step_locked()
                if self.done:
                    m._finished(self)
        return self.done

    def _step_locked(self) -> None:
        m = self._memory
        if self.done:
            return
        if m._closed and m.config.storage_dir:   # its log is closed: nothing more may be applied
            raise MemoryInputError(f"store: the memory was closed after {self.applied} of {self.n} "
                                   "transitions of this batch were stored")
        m.tm.expire(m._clock)
        a, b = self.applied, min(self.n, self.applied + self.chunk)
        part = self._t if (a, b) == (0, self.n) else self._t.take(slice(a, b))
        self._parts.append(m._store_chunk(part, self._keys[a:b]))
        self.applied = b
        if self.done:   # a remembered answer keeps its ids only, not the batch (resend_window: 8 bytes each)
            self._t = self._keys = None

    def result(self) -> StoreResult:
        """The whole batch's StoreResult (applies the chunks still left first)."""
        while not self.done:
            self.step()
        p = self._parts
        if len(p) == 1:
            return p[0]
        return StoreResult(np.concatenate([r.identity_ids for r in p]), sum(r.new_identities for r in p),
                           sum(r.similarity_hits for r in p), sum(r.evicted for r in p), p[-1].wal_sequence)


class _Repeated:
    """A re-sent store's view of the original :class:`ChunkedStore` (every attribute but ``repeated``)."""

    repeated = True

    def __init__(self, op: ChunkedStore):
        self._op = op

    def __getattr__(self, name):
        return getattr(self._op, name)
