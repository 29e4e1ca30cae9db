"""CompactMemory: identities, similar-transition sets, TM, RTM, two-phase reduction, sampling.

Operations follow method.md section 2. The memory composes its parts and holds the one lock
that protects them all (the ROS node may call from a multi-threaded executor):

* :class:`~.slots.SlotTable` -- per-identity columns, id <-> slot map, keys for the index;
* :class:`~.tables.TransitionTable` (TM, FIFO with leases) and :class:`~.tables.ReducedTable`
  (RTM, uniform), with the :class:`~.tables.Remover` that enforces the capacities;
* :class:`~.reduction.Reduction` -- the two-phase reduction: leases out of TM, commits into RTM;
* the similarity index (:func:`~.index.make_index`), which decides what each stored
  transition joins;
* :class:`~.memory_state.MemoryState` -- all of the above as one object: what a snapshot holds,
  how a validated operation and a replayed WAL record are applied;
* :class:`~.durability.Durability` -- WAL, snapshots, recovery (when ``storage_dir`` is set);
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
from .chunked_store import ChunkedStore, StoreTarget
from .durability import COUNTERS, Durability, check_arrays, t_to_arrays
from .key_norm import resolve_store
from .memory_state import MemoryState
from .results import (CommitResult, LeaseError, MemoryInputError, ReductionLease, SampleResult,
                      StoreResult, newest_label)
from .validation import schema_of, validate_store

__all__ = ["CompactMemory", "ChunkedStore", "MemoryInputError", "LeaseError", "StoreResult", "SampleResult",
           "ReductionLease", "CommitResult", "newest_label"]


class CompactMemory:
    """The compact memory (see module docstring and docs/memory.md)."""

    #: the state's parts and counters, read through the memory (``memory.slots``, ``memory.wal_sequence``, ...)
    _STATE_VIEW = frozenset({"schema", "index", "key_norm", "slots", "a", "tm", "rtm", "remover", "reduction",
                             "stores", "expected_key_size", *COUNTERS})

    def __init__(self, config: MemoryConfig | None = None, key_size: int | None = None, *,
                 clock: Callable[[], float] = time.monotonic,
                 log: Callable[[str], None] | None = None):
        """log(text): where start-up warnings go (a torn WAL tail dropped, leftovers of an
        interrupted snapshot, accepted WAL loss); default the ``comper_memory`` Python logger."""
        self.config = (config or MemoryConfig()).validate()
        self._log = log or logging.getLogger("comper_memory").warning
        self.state = MemoryState(self.config, key_size)
        self._clock = clock
        self._lock = threading.RLock()
        self._durable: Durability | None = None
        self._closed = False

        def check_open() -> None:      # a chunk may be applied: not after close() of a memory with a log
            if self._closed and self.config.storage_dir:
                raise MemoryInputError("the memory was closed")

        def after_chunk() -> None:     # a chunk and the registry's record of it are in: a checkpoint may hold both
            if self._durable is not None:
                self._durable.maybe_checkpoint()

        # what a chunked store is applied to (chunked_store.StoreTarget): no reach into this object
        self._target = StoreTarget(lock=self._lock, registry=self.state.stores, check_open=check_open,
                                   apply_chunk=self._store_chunk, after_chunk=after_chunk)
        c = self.config
        self.rate = RateLimiter(c.min_size_to_sample, c.samples_per_insert, c.rate_error_buffer)
        if self.config.storage_dir:
            self._durable = Durability(self.config, self._log, state=self.state.arrays,
                                       sequence=lambda: self.state.wal_sequence)
            self._durable.open(lambda arrays, meta: self.state.restore(arrays, meta, self._target),
                               lambda seq, kind, arr: self.state.replay(seq, kind, arr, self._target))
            self.rate.recovered(self.state.slots.n_live)

    def __getattr__(self, name: str):
        if name in CompactMemory._STATE_VIEW:     # only reached for names the memory itself does not have
            return getattr(self.state, name)
        raise AttributeError(f"{type(self).__name__!r} object has no attribute {name!r}")

    @property
    def index_engine(self) -> str | None:
        """The index engine forced for the next schema (None: the config's ``index_engine``)."""
        return self.state.index_engine

    @index_engine.setter
    def index_engine(self, engine: str | None) -> None:
        self.state.index_engine = engine

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
            state = self.state
            same = state.stores.known(rid)
            if same is not None and not same.needs_batch:
                return same.repeat()
            state.tm.expire(self._clock)
            clean, keys = validate_store(t, self.config, state.schema, state.expected_key_size)
            if same is not None:   # cut short by a restart: the rest of it, admitted when it was first sent
                same.resume(clean, keys, chunk)
                self.rate.inserted(same.n - same.applied, relabel)
                same.step_locked()
                return same.repeat()
            if not relabel:
                self.rate.check_insert(len(clean), state.slots.n_live)
            if state.schema is None:
                state.init_schema(schema_of(clean))
            op = ChunkedStore(self._target, clean, keys, int(chunk) if chunk and chunk > 0 else len(clean), rid)
            op.step_locked()
            self.rate.inserted(len(clean), relabel)   # admitted whole: later chunks are not checked again
            return op

    def _store_chunk(self, clean: Transitions, keys: np.ndarray, request: np.ndarray | None) -> StoreResult:
        """One logged store of a validated batch (the lock is held); ``request``: [request id, offset of
        this chunk, batch size] for a store whose answer is remembered, logged with it."""
        state = self.state
        state.tm.expire(self._clock)
        y, res = resolve_store(state.index, state.key_norm, keys)
        if self._durable is not None:
            record = t_to_arrays(clean, state.slots.obs.layout)
            if request is not None:
                record["request"] = request
            self._durable.append(state.wal_sequence + 1, st.WAL_STORE, record)
        state.wal_sequence += 1
        return state.apply_store(clean, y, res, keys)

    # ================================================================== reduction
    def begin_reduce(self, max_sets: int | None = None) -> ReductionLease:
        """Pop up to max_sets (default reduce_batch) oldest TM sets into a lease for the QT."""
        with self._lock:
            state = self.state
            state.tm.expire(self._clock)
            k = self.config.reduce_batch if max_sets is None else int(max_sets)
            if k < 0:
                raise MemoryInputError(f"begin_reduce: max_sets must be >= 0, got {k}")
            rid = state.next_reduction_id
            state.next_reduction_id += 1
            return state.reduction.lease(k, rid, self._clock() + self.config.lease_timeout_s, state.schema)

    def commit_reduce(self, reduction_id: int, identity_ids: np.ndarray,
                      predictions: np.ndarray) -> CommitResult:
        """Upsert the lease's identities into RTM with the QT's predictions."""
        with self._lock:
            state = self.state
            state.tm.expire(self._clock)
            rid = int(reduction_id)
            commit = state.reduction.check_commit(rid, identity_ids, predictions)
            if self._durable is not None:
                self._durable.append(state.wal_sequence + 1, st.WAL_COMMIT, commit)
            state.wal_sequence += 1
            del state.tm.leases[rid]
            out = state.apply_commit(rid, **commit)
            if self._durable is not None:
                self._durable.maybe_checkpoint()
            return out

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
            state = self.state
            state.tm.expire(self._clock)
            if source not in ("rtm", "tm"):
                raise MemoryInputError(f"sample: source must be 'rtm' or 'tm', got {source!r}")
            k, nb = int(k), max(1, int(num_batches))
            if k < 0 or k * nb > self.config.max_sample_batch:
                raise MemoryInputError(f"sample: k={k} x num_batches={nb} outside [0, max_sample_batch="
                                       f"{self.config.max_sample_batch}]")
            self.rate.check_sample(k * nb, state.slots.n_live)   # before the size checks: a sampler may wait to fill
            table = state.rtm if source == "rtm" else state.tm
            if k > table.n:
                if not allow_fewer:
                    raise MemoryInputError(f"sample: k={k} exceeds the {table.n} entries of {source.upper()}")
                k = table.n
            if state.schema is None:
                raise MemoryInputError("sample: the memory is empty")
            rng = rng if rng is not None else np.random.default_rng(seed)
            slots = table.sample(k, nb, rng)
            self.rate.sampled(k * nb)
            return SampleResult(state.slots.reps(slots, table.labels(slots)), state.a["id"][slots].copy(),
                                state.a["count"][slots].copy(), source)

    # ================================================================== introspection
    @property
    def rtm_size(self) -> int:
        with self._lock:
            self.state.tm.expire(self._clock)
            return self.state.rtm.n

    @property
    def tm_size(self) -> int:
        with self._lock:
            self.state.tm.expire(self._clock)
            return self.state.tm.n

    @property
    def key_size(self) -> int | None:
        state = self.state
        return state.schema["key_size"] if state.schema else state.expected_key_size

    def bytes_used(self) -> int:
        with self._lock:
            state = self.state
            b = state.slots.bytes_used() + state.tm.bytes_used() + state.rtm.bytes_used()
            if state.index is not None:
                b += state.index.bytes_used()
            return int(b)

    def stats(self) -> dict:
        with self._lock:
            state = self.state
            state.tm.expire(self._clock)
            n = state.transitions_stored
            return {
                "key_size": self.key_size or 0, "delta": self.config.delta,
                "identities": state.slots.n_live, "tm_sets": state.tm.n, "rtm_size": state.rtm.n,
                "transitions_stored": n, "similarity_hits": state.similarity_hits,
                "hit_rate": state.similarity_hits / n if n else 0.0,
                "compaction_ratio": state.rtm.n / n if n else 0.0,
                "reductions": state.reductions, "sets_reduced": state.sets_reduced,
                "evictions": state.evictions, "bytes_used": self.bytes_used(),
                "wal_sequence": state.wal_sequence, "leases": len(state.tm.leases),
                **state.key_norm.stats(),
            }

    def rate_stats(self) -> dict:
        """The rate limiter's counts (RateLimiter.stats): of this process's life, not the memory's state."""
        with self._lock:
            return self.rate.stats()

    # ================================================================== snapshots
    def export_state(self) -> tuple[dict[str, np.ndarray], dict]:
        """(arrays, meta) exactly as a snapshot would hold them (live identities ordered by id)."""
        with self._lock:
            return self.state.arrays()

    def save_snapshot(self, path: str, admit=None) -> None:
        """Write the whole state to the snapshot directory ``path`` (atomic, checksummed). ``admit(arrays,
        meta)``, if given, sees what will be written before anything is; what it raises refuses the save."""
        with self._lock:
            arrays, meta = self.state.arrays()
            if admit is not None:
                admit(arrays, meta)
            st.write_snapshot(path, arrays, meta)

    def load_snapshot(self, path: str) -> None:
        """Replace the state by the snapshot at ``path``; refused (state untouched) if it is bad."""
        with self._lock:
            state = self.state
            if state.stores.any_in_progress():
                raise MemoryInputError("restore: a large store is being applied in chunks; restore once "
                                       "it is answered (a restore would replace the state under it)")
            arrays, meta = st.read_snapshot(path)
            check_arrays(arrays)
            seq = state.wal_sequence
            state.restore(arrays, meta, self._target)   # the snapshot's remembered answers replace ours
            self.rate.recovered(state.slots.n_live)
            if self._durable is not None:
                # the restore is an operation at the current log position: the new snapshot keeps
                # the sequence monotone, so the older log files it replaces are never replayed
                # over it after a kill between the snapshot and their deletion
                state.wal_sequence = max(seq, state.wal_sequence)
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

