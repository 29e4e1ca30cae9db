"""Stores applied in chunks, and the stores a memory remembers by request id.

* :class:`ChunkedStore` -- a validated batch being applied chunk by chunk (like Reverb's
  writer with a chunk length): :meth:`CompactMemory.begin_store` applies its first chunk,
  ``step()`` the next ones, each under its own hold of the memory's lock.
* :class:`StoreRegistry` -- the stores still in progress (a restore waits for them) and the
  answers of finished stores with a request id, kept up to ``resend_window`` transitions, so a
  re-sent store is answered without being applied twice (docs/memory-service.md). The registry
  is part of the memory's durable state: each chunk's WAL record carries its request id, position
  and batch size, and a snapshot holds the registry (``arrays``/``load``), so a restarted memory
  still knows its answers, and a batch cut short by a crash between chunks is completed, not
  applied twice, when its client re-sends it.

The memory owns one registry; every method of it is called with the memory's lock held. What a chunked
store needs of the memory is one explicit :class:`StoreTarget` the memory makes: its lock, its registry
and the step that logs and applies one chunk.
"""
from __future__ import annotations

import threading
import weakref
from collections import OrderedDict
from dataclasses import dataclass
from typing import Callable

import numpy as np

from comper_msgs_py.arrays import Transitions

from .results import MemoryInputError, StoreResult

__all__ = ["ChunkedStore", "StoreRegistry", "StoreTarget", "REGISTRY_ARRAYS", "check_registry"]


@dataclass(frozen=True)
class StoreTarget:
    """What a :class:`ChunkedStore` is applied to: the memory's lock and registry, and three steps the memory
    gives (each called with the lock held): ``check_open()`` raises MemoryInputError once nothing more may be
    applied, ``apply_chunk(part, keys, request)`` logs and applies one chunk and returns its StoreResult,
    ``after_chunk()`` runs once the registry has recorded the chunk (a checkpoint then holds both)."""

    lock: threading.RLock
    registry: "StoreRegistry"
    check_open: Callable[[], None]
    apply_chunk: Callable[[Transitions, np.ndarray, np.ndarray | None], StoreResult]
    after_chunk: Callable[[], None]


class ChunkedStore:
    """A validated store being applied chunk by chunk (:meth:`CompactMemory.begin_store`).

    ``step()`` applies the next chunk under the memory's lock and returns ``done``; between two
    steps the lock is free, so other calls run. ``result()`` applies whatever is left and returns
    the StoreResult of the whole batch. After the memory is closed a step raises
    MemoryInputError (nothing more is applied or logged); ``applied`` says how many transitions
    are in the memory then."""

    def __init__(self, target: StoreTarget, clean: Transitions | None, keys: np.ndarray | None, chunk: int,
                 request_id: int = 0, n: int | None = None):
        self._target = target
        self._t, self._keys, self.chunk = clean, keys, max(1, int(chunk))
        self.n = len(clean) if n is None else int(n)
        self.request_id = int(request_id)
        self.applied = 0
        self._parts: list[StoreResult] = []
        #: for a store recovered part-applied (needs_batch): the registry's finished transitions at its recovery
        self.recovered_at: int | None = None

    @property
    def needs_batch(self) -> bool:
        """Recovered after a restart with chunks left: its batch comes again with the client's re-send."""
        return not self.done and self._t is None

    def resume(self, clean: Transitions, keys: np.ndarray, chunk: int) -> None:
        """Take the re-sent batch of a store recovered part-applied (:attr:`needs_batch`); its chunks
        from ``applied`` on are applied from it. MemoryInputError if it is not the same size."""
        if len(clean) != self.n:
            raise MemoryInputError(
                f"store: request id {self.request_id} was a batch of {self.n} transitions, {self.applied} of them "
                f"stored before the memory restarted; this re-send has {len(clean)} (a request id names one batch)")
        self._t, self._keys = clean, keys
        if chunk and chunk > 0:
            self.chunk = int(chunk)

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
        with self._target.lock:
            self.step_locked()
        return self.done

    def step_locked(self) -> None:
        """Apply the next chunk and record it in the registry (a checkpoint after it holds both); the
        caller holds the memory's lock."""
        t = self._target
        if self.done:
            return
        try:
            t.check_open()
        except MemoryInputError as exc:
            raise MemoryInputError(f"store: {exc} after {self.applied} of {self.n} transitions of this batch "
                                   "were stored") from None
        a, b = self.applied, min(self.n, self.applied + self.chunk)
        part = self._t if (a, b) == (0, self.n) else self._t.take(slice(a, b))
        request = t.registry.request_record(self, a)
        self.chunk_applied(t.apply_chunk(part, self._keys[a:b], request))
        if self.done:   # a remembered answer keeps its ids only, not the batch (resend_window: 8 bytes each)
            self._t = self._keys = None
        t.after_chunk()

    def chunk_applied(self, part: StoreResult) -> None:
        """One more chunk of this batch is in the memory (applied live, or replayed from the WAL)."""
        self._parts.append(part)
        self.applied += len(part.identity_ids)
        self._target.registry.progressed(self)

    def result(self) -> StoreResult:
        """The whole batch's StoreResult (applies the chunks still left first)."""
        while not self.done:
            self.step()
        return self.result_so_far()

    def result_so_far(self) -> StoreResult:
        """The StoreResult of the chunks applied so far (``result()`` once done)."""
        p = self._parts
        if not p:
            return StoreResult(np.zeros(0, np.int64), 0, 0, 0, 0)
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


#: a snapshot's registry: one row per store (request id, batch size, transitions applied, new
#: identities, similarity hits, evicted, last WAL sequence), oldest answer first, then the stores cut
#: short; and the identity ids of the applied transitions of every row, concatenated in that order
_REQUEST_COLUMNS = 7
_ROWS, _IDS = REGISTRY_ARRAYS = ("resend_requests", "resend_identity_ids")


class StoreRegistry:
    """Stores in progress, and finished stores' answers by request id (oldest first, at most
    ``resend_window`` transitions of them, but always the newest one); 0 turns ids off.

    A store a restart cut short (:attr:`ChunkedStore.needs_batch`) waits for its client's re-send
    until ``resend_window`` transitions of other stores have finished after its recovery; then it is
    forgotten like an old answer (a later re-send is applied as a new store)."""

    def __init__(self, resend_window: int):
        self.resend_window = int(resend_window)
        self._in_progress: weakref.WeakSet = weakref.WeakSet()   # a restore waits for these
        self._pending_ids: dict[int, ChunkedStore] = {}           # in progress, by request id
        self._answers: OrderedDict[int, ChunkedStore] = OrderedDict()   # finished, by request id
        self._answers_size = 0                                    # transitions of the answers
        self._finished_total = 0                                  # transitions of stores finished here

    def tracks(self, rid: int) -> bool:
        return rid > 0 and self.resend_window > 0

    def known(self, rid: int) -> ChunkedStore | None:
        """The store with request id ``rid`` still in progress or remembered, else None."""
        if not self.tracks(rid):
            return None
        return self._pending_ids.get(rid) or self._answers.get(rid)

    def request_record(self, op: ChunkedStore, offset: int) -> np.ndarray | None:
        """The WAL record's ``request`` field of op's chunk at ``offset``: [request id, offset, batch size],
        or None for a store without a tracked id."""
        if not self.tracks(op.request_id):
            return None
        return np.array([op.request_id, offset, op.n], dtype=np.int64)

    def progressed(self, op: ChunkedStore) -> None:
        """``op`` applied another chunk: in progress while chunks are left, remembered once done."""
        if op.done:
            self._finished(op)
            return
        if not op.needs_batch:
            self._in_progress.add(op)
        if self.tracks(op.request_id):
            self._pending_ids[op.request_id] = op
            if op.needs_batch and op.recovered_at is None:
                op.recovered_at = self._finished_total

    def _finished(self, op: ChunkedStore) -> None:
        """``op`` is fully applied: remember its answer by its request id."""
        self._in_progress.discard(op)
        rid = op.request_id
        if not self.tracks(rid):
            return
        self._pending_ids.pop(rid, None)
        self._answers[rid] = op
        self._answers_size += op.n
        self._finished_total += op.n
        while self._answers_size > self.resend_window and len(self._answers) > 1:
            _, old = self._answers.popitem(last=False)
            self._answers_size -= old.n
        for old_rid in [r for r, p in self._pending_ids.items()   # cut short and never re-sent: forgotten, as an
                        if p.needs_batch and self._finished_total - p.recovered_at > self.resend_window]:
            del self._pending_ids[old_rid]                       # answer this old would be

    def any_in_progress(self) -> bool:
        return any(not op.done for op in self._in_progress)

    def replayed(self, target: StoreTarget, request: np.ndarray, part: StoreResult) -> None:
        """A WAL record of a chunk with request ``[id, offset, n]`` was replayed with result ``part``."""
        rid, offset, n = (int(v) for v in request)
        if not self.tracks(rid):
            return
        op = self._pending_ids.get(rid)
        if op is None and offset == 0:
            self._recovered(target, rid, n, part)
        elif op is None or op.applied != offset or op.n != n:   # the log and the snapshot disagree: forget it
            self._pending_ids.pop(rid, None)
        else:
            op.chunk_applied(part)

    def _recovered(self, target: StoreTarget, rid: int, n: int, part: StoreResult) -> None:
        """A store of n transitions known from the WAL or a snapshot, ``part`` of it applied: remembered if
        whole, else waiting for its client's re-send (:attr:`ChunkedStore.needs_batch`)."""
        ChunkedStore(target, None, None, len(part.identity_ids), rid, n=n).chunk_applied(part)

    def arrays(self) -> dict[str, np.ndarray]:
        """The registry as a snapshot holds it (REGISTRY_ARRAYS)."""
        ops = list(self._answers.values()) + [op for op in self._pending_ids.values() if op.applied]
        rows = np.zeros((len(ops), _REQUEST_COLUMNS), dtype=np.int64)
        ids = []
        for i, op in enumerate(ops):
            r = op.result_so_far()
            rows[i] = (op.request_id, op.n, op.applied, r.new_identities, r.similarity_hits, r.evicted,
                       r.wal_sequence)
            ids.append(r.identity_ids)
        return {_ROWS: rows, _IDS: np.concatenate(ids).astype(np.int64) if ids else np.zeros(0, np.int64)}

    def load(self, target: StoreTarget, arrays: dict[str, np.ndarray]) -> None:
        """Replace the answers by a snapshot's (none in a snapshot written before they were kept); the
        caller has checked them (:func:`check_registry`). Stores in progress here are not touched."""
        self._answers.clear()
        self._answers_size = 0
        self._pending_ids = {rid: op for rid, op in self._pending_ids.items() if not op.needs_batch}
        rows = arrays.get(_ROWS, np.zeros((0, _REQUEST_COLUMNS), np.int64))
        ids = arrays.get(_IDS, np.zeros(0, np.int64))
        at = 0
        for rid, n, applied, new, hits, evicted, seq in rows.tolist():
            part = StoreResult(ids[at:at + applied].copy(), new, hits, evicted, seq)
            at += applied
            if self.tracks(rid):
                self._recovered(target, rid, n, part)


def check_registry(arrays: dict[str, np.ndarray]) -> str | None:
    """What is wrong with a snapshot's registry arrays, or None."""
    rows, ids = arrays.get(_ROWS), arrays.get(_IDS)
    if rows is None and ids is None:
        return None
    if rows is None or ids is None or rows.ndim != 2 or rows.shape[1] != _REQUEST_COLUMNS:
        return f"resend arrays {REGISTRY_ARRAYS} are incomplete or misshapen"
    n, applied = rows[:, 1], rows[:, 2]
    if (rows[:, 0] <= 0).any() or (applied <= 0).any() or (applied > n).any() or int(applied.sum()) != len(ids):
        return "resend arrays: request ids, batch sizes and applied counts do not agree with the identity ids"
    if len(np.unique(rows[:, 0])) != len(rows):
        return "resend arrays: a request id appears twice"
    return None
