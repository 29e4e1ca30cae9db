"""Stores applied in chunks, and the stores a memory remembers by request id.

* :class:`ChunkedStore` -- a validated batch being applied chunk by chunk (like Reverb's
  writer with a chunk length): :meth:`CompactMemory.begin_store` applies its first chunk,
  ``step()`` the next ones, each under its own hold of the memory's lock.
* :class:`StoreRegistry` -- the stores still in progress (a restore waits for them) and the
  answers of finished stores with a request id, kept up to ``resend_window`` transitions, so a
  re-sent store is answered without being applied twice (docs/memory-service.md).

The memory owns one registry; every method of it is called with the memory's lock held.
"""
from __future__ import annotations

import weakref
from collections import OrderedDict
from typing import TYPE_CHECKING

import numpy as np

from comper_msgs_py.arrays import Transitions

from .results import MemoryInputError, StoreResult

if TYPE_CHECKING:
    from .memory import CompactMemory

__all__ = ["ChunkedStore", "StoreRegistry"]


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
                self.step_locked()
                if self.done:
                    m.stores.finished(self)
        return self.done

    def step_locked(self) -> None:
        """Apply the next chunk; the caller holds the memory's lock."""
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


class StoreRegistry:
    """Stores in progress, and finished stores' answers by request id (oldest first, at most
    ``resend_window`` transitions of them, but always the newest one); 0 turns ids off."""

    def __init__(self, resend_window: int):
        self.resend_window = int(resend_window)
        self._in_progress: weakref.WeakSet = weakref.WeakSet()   # a restore waits for these
        self._pending_ids: dict[int, ChunkedStore] = {}           # in progress, by request id
        self._answers: OrderedDict[int, ChunkedStore] = OrderedDict()   # finished, by request id
        self._answers_size = 0                                    # transitions of the answers

    def _tracks(self, rid: int) -> bool:
        return rid > 0 and self.resend_window > 0

    def known(self, rid: int) -> ChunkedStore | None:
        """The store with request id ``rid`` still in progress or remembered, else None."""
        if not self._tracks(rid):
            return None
        return self._pending_ids.get(rid) or self._answers.get(rid)

    def started(self, op: ChunkedStore) -> None:
        """``op`` has chunks left after its first one."""
        self._in_progress.add(op)
        if self._tracks(op.request_id):
            self._pending_ids[op.request_id] = op

    def finished(self, op: ChunkedStore) -> None:
        """``op`` is fully applied: remember its answer by its request id."""
        self._in_progress.discard(op)
        rid = op.request_id
        if not self._tracks(rid):
            return
        self._pending_ids.pop(rid, None)
        self._answers[rid] = op
        self._answers_size += op.n
        while self._answers_size > self.resend_window and len(self._answers) > 1:
            _, old = self._answers.popitem(last=False)
            self._answers_size -= old.n

    def any_in_progress(self) -> bool:
        return any(not op.done for op in self._in_progress)

    def forget_answers(self) -> None:
        """The state was replaced (a restore): the remembered answers describe the old one."""
        self._answers.clear()
        self._answers_size = 0
