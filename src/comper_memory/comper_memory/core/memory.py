"""CompactMemory: identities, similar-transition sets, TM, RTM, two-phase reduction, sampling.

Operations follow method.md section 2. The memory composes its parts and holds the one lock
that protects them all (the ROS node may call from a multi-threaded executor):

* :class:`~.slots.SlotTable` -- per-identity columns, id <-> slot map, keys for the index;
* :class:`~.tables.TransitionTable` (TM, FIFO with leases) and :class:`~.tables.ReducedTable`
  (RTM, uniform), with the :class:`~.tables.Remover` that enforces the capacities;
* :class:`~.reduction.Reduction` -- the two-phase reduction: leases out of TM, commits into RTM;
* the similarity index (:func:`~.index.make_index`), which decides what each stored
  transition joins;
* :class:`~.durability.Durability` -- WAL, snapshots, recovery (when ``storage_dir`` is set),
  with :mod:`.memory_state` saying what of the memory a snapshot holds and how a WAL record is
  replayed;
* :class:`~.chunked_store.StoreRegistry` -- large stores applied in chunks
  (:class:`~.chunked_store.ChunkedStore`) and re-sent stores answered by request id.

Every operation is validated whole first (:mod:`.validation`), then logged, then applied, so
a refused request changes nothing and a replayed log rebuilds the same state.
"""
from __future__ import annotations

import logging
import threading
import time
from typing import Callable

import numpy as np

from comper_msgs_py.arrays import Transitions

from . import storage as st
from .config import MemoryConfig
from .rate_limiter import RateLimited, RateLimiter
from .chunked_store import ChunkedStore, StoreRegistry
from .durability import COUNTERS, Durability, check_arrays, t_to_arrays
from .index import make_index
from .key_norm import KeyNormaliser, resolve_store
from .memory_state import replay_record, restore_state, state_arrays
from .results import (CommitResult, LeaseError, MemoryInputError, ReductionLease, SampleResult,
                      StoreResult, newest_label)
from .reduction import Reduction
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
        # chunked stores in progress and re-sent stores' answers by request id
        self.stores = StoreRegistry(self.config.resend_window)
        self._reset_state()
        c = self.config
        self.rate = RateLimiter(c.min_size_to_sample, c.samples_per_insert, c.rate_error_buffer)
        if self.config.storage_dir:
            self._durable = Durability(self.config, self._log, state=lambda: state_arrays(self),
                                       sequence=lambda: self.wal_sequence)
            self._durable.open(lambda arrays, meta: restore_state(self, arrays, meta),
                               lambda seq, kind, arr: replay_record(self, seq, kind, arr))
            self.rate.recovered(self.slots.n_live)

    # ================================================================== parts
    def _reset_state(self) -> None:
        c = self.config
        self.schema: dict | None = None   # obs_shape, obs_dtype, action_shape, action_dtype, key_size
        self.index: SimilarityIndex | None = None
        self.key_norm = KeyNormaliser(c.key_normalisation, c.key_norm_growth, c.key_norm_min_std)
        self.slots = SlotTable(c.history_length, c.frame_scale, self.key_norm)
        self.a = self.slots.a   # the slot columns (one dict for the table's life; tests read it)
        self.tm = TransitionTable(self.slots)
        self.rtm = ReducedTable(self.slots)
        self.remover = Remover(self.slots, self.tm, self.rtm, c.rtm_capacity, c.tm_capacity)
        self.reduction = Reduction(self.slots, self.tm, self.rtm)
        for name in COUNTERS:
            setattr(self, name, 0)
        self.next_reduction_id = 1

    def _init_schema(self, schema: dict) -> None:
        self.schema = schema
        self.slots.schema = schema
        key = index_key_size(schema["obs_shape"], schema["action_shape"])
        self.index = make_index(self.config, key, self.slots, self.index_engine)

    # ================================================================== store
    def store(self, t: Transitions, request_id: int = 0, relabel: bool = False) -> StoreResult:
        """Store a batch (thesis Algorithm 6), atomically; raise MemoryInputError on bad input.
        request_id (0 = none), relabel: see :meth:`begin_store`."""
        return self.begin_store(t, chunk=0, request_id=request_id, relabel=relabel).result()

    def begin_store(self, t: Transitions, chunk: int = 0, request_id: int = 0,
                    relabel: bool = False) -> ChunkedStore:
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
        True; step it like any other), before validation and the rate limiter.

        relabel: the batch is transitions stored once already, sent again with fresh value labels
        (``restore_batch``); stored like any other, but the rate limiter neither holds it back nor
        counts it as inserts (:mod:`.rate_limiter`)."""
        with self._lock:
            rid = int(request_id)
            same = self.stores.known(rid)
            if same is not None and not same.needs_batch:
                return same.repeat()
            self.tm.expire(self._clock)
            clean, keys = validate_store(t, self.config, self.schema, self.expected_key_size)
            if same is not None:   # cut short by a restart: the rest of it, admitted when it was first sent
                same.resume(clean, keys, chunk)
                self.rate.inserted(same.n - same.applied, relabel)
                same.step_locked()
                return same.repeat()
            if not relabel:
                self.rate.check_insert(len(clean), self.slots.n_live)
            if self.schema is None:
                self._init_schema(schema_of(clean))
            op = ChunkedStore(self, clean, keys, int(chunk) if chunk and chunk > 0 else len(clean), rid)
            op.step_locked()
            self.rate.inserted(len(clean), relabel)   # admitted whole: later chunks are not checked again
            return op

    def _store_chunk(self, clean: Transitions, keys: np.ndarray, request: np.ndarray | None) -> StoreResult:
        """One logged store of a validated batch (the lock is held); ``request``: [request id, offset of
        this chunk, batch size] for a store whose answer is remembered, logged with it."""
        y, res = resolve_store(self.index, self.key_norm, keys)
        if self._durable is not None:
            record = t_to_arrays(clean)
            if request is not None:
                record["request"] = request
            self._durable.append(self.wal_sequence + 1, st.WAL_STORE, record)
        self.wal_sequence += 1
        return self._apply_store(clean, y, res, keys)

    def _apply_store(self, t: Transitions, y: np.ndarray, res: ResolveResult, raw_keys: np.ndarray) -> StoreResult:
        n = len(t)
        self.key_norm.observe(raw_keys)
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
            return self.reduction.lease(k, rid, self._clock() + self.config.lease_timeout_s, self.schema)

    def commit_reduce(self, reduction_id: int, identity_ids: np.ndarray,
                      predictions: np.ndarray) -> CommitResult:
        """Upsert the lease's identities into RTM with the QT's predictions."""
        with self._lock:
            self.tm.expire(self._clock)
            rid = int(reduction_id)
            commit = self.reduction.check_commit(rid, identity_ids, predictions)
            if self._durable is not None:
                self._durable.append(self.wal_sequence + 1, st.WAL_COMMIT, commit)
            self.wal_sequence += 1
            del self.tm.leases[rid]
            out = self._apply_commit(rid, **commit)
            if self._durable is not None:
                self._durable.maybe_checkpoint()
            return out

    def _apply_commit(self, rid, ids, preds, in_tm, tm_key, replay: bool = False) -> CommitResult:
        n = self.reduction.apply(rid, ids, preds, in_tm, tm_key, replay)
        if self.key_norm.maybe_freeze():   # new mean/scale: every identity's key changes
            self.index = make_index(self.config, self.index.key_dim, self.slots, self.index_engine)
            self.index.reindex()
        self.reductions += 1
        self.sets_reduced += n
        return CommitResult(rid, n, len(ids) - n, self.wal_sequence)

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
                **self.key_norm.stats(),
            }

    def rate_stats(self) -> dict:
        """The rate limiter's counts (RateLimiter.stats): of this process's life, not the memory's state."""
        with self._lock:
            return self.rate.stats()

    # ================================================================== snapshots
    def export_state(self) -> tuple[dict[str, np.ndarray], dict]:
        """(arrays, meta) exactly as a snapshot would hold them (live identities ordered by id)."""
        with self._lock:
            return state_arrays(self)

    def save_snapshot(self, path: str, admit=None) -> None:
        """Write the whole state to the snapshot directory ``path`` (atomic, checksummed). ``admit(arrays,
        meta)``, if given, sees what will be written before anything is; what it raises refuses the save."""
        with self._lock:
            arrays, meta = state_arrays(self)
            if admit is not None:
                admit(arrays, meta)
            st.write_snapshot(path, arrays, meta)

    def load_snapshot(self, path: str) -> None:
        """Replace the state by the snapshot at ``path``; refused (state untouched) if it is bad."""
        with self._lock:
            if self.stores.any_in_progress():
                raise MemoryInputError("restore: a large store is being applied in chunks; restore once "
                                       "it is answered (a restore would replace the state under it)")
            arrays, meta = st.read_snapshot(path)
            check_arrays(arrays)
            seq = self.wal_sequence
            restore_state(self, arrays, meta)   # the snapshot's remembered answers replace ours
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

